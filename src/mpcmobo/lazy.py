"""Names of a package imported from their modules when first used (PEP 562).

A package that re-exports heavy modules (torch, BoTorch) defines ``_WHERE`` (name -> module
within the package) and ``__getattr__, __dir__ = lazy_names(__name__, _WHERE, __all__)``;
importing one of its light modules then imports none of the heavy ones.
"""

from __future__ import annotations

import importlib
import sys
from collections.abc import Callable, Mapping, Sequence
from typing import Any

__all__ = ["lazy_names"]


def lazy_names(
    package: str, where: Mapping[str, str], names: Sequence[str]
) -> tuple[Callable[[str], Any], Callable[[], list[str]]]:
    """The module ``__getattr__`` and ``__dir__`` of ``package``: a name of ``where`` is
    imported from its module on first use, then kept in the package's namespace."""

    def __getattr__(name: str) -> Any:
        if name in where:
            value = getattr(importlib.import_module(f"{package}.{where[name]}"), name)
            setattr(sys.modules[package], name, value)
            return value
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__() -> list[str]:
        return sorted({*vars(sys.modules[package]), *names})

    return __getattr__, __dir__
