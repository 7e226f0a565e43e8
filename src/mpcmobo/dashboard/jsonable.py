"""Numbers as the page's JSON holds them: plain lists, with null for NaN and infinities."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

__all__ = ["floats", "floats2", "number", "plain"]


def floats(values: Any) -> list[float | None]:
    """A 1-D sequence of numbers as a list, None where a value is not finite."""
    a = np.asarray(values, dtype=float).ravel()
    return [float(v) if math.isfinite(v) else None for v in a.tolist()]


def floats2(values: Any) -> list[list[float | None]]:
    """A 2-D array as a list of :func:`floats` rows."""
    return [floats(row) for row in np.asarray(values, dtype=float)]


def number(value: Any) -> float | None:
    """One number, None if it is missing or not finite."""
    try:
        f = float(value)
    except (TypeError, ValueError):
        return None
    return f if math.isfinite(f) else None


def plain(obj: Any) -> Any:
    """Any JSON-like value with numpy types made plain and non-finite numbers as None."""
    if isinstance(obj, dict):
        return {str(k): plain(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return plain(obj.tolist())
    if isinstance(obj, bool | np.bool_):
        return bool(obj)
    if isinstance(obj, int | np.integer):
        return int(obj)
    if isinstance(obj, float | np.floating):
        return number(obj)
    return obj
