"""A run's files read while the run writes them: cached by modification time and size, and
never raising.

:class:`FileCache` reads a file again only when its ``(mtime_ns, size)`` changed since the last
read; a file that cannot be read (half-written, truncated, not Parquet) gives a
:class:`FileRead` with a message naming the file and the problem instead of its value, and the
next change of the file is read again.
"""

from __future__ import annotations

import json
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from mpcmobo.experiment import storage

__all__ = ["FileCache", "FileRead", "describe", "read_json", "read_parquet", "read_pickle"]

Stamp = tuple[int, int]


@dataclass(frozen=True)
class FileRead:
    """What reading one file gave: its ``value`` (None if the file is missing or damaged),
    ``error`` (a message naming the file, None if it was read or is missing) and its
    ``stamp`` (``(mtime_ns, size)``; None if it is missing)."""

    value: Any
    error: str | None
    stamp: Stamp | None

    @property
    def ok(self) -> bool:
        """Whether the file exists and was read."""
        return self.stamp is not None and self.error is None


def describe(err: BaseException) -> str:
    """``err`` in one line: its type and the first line of its message."""
    lines = str(err).strip().splitlines()
    return f"{type(err).__name__}: {lines[0]}" if lines else type(err).__name__


def stamp(path: Path) -> Stamp | None:
    """``(mtime_ns, size)`` of ``path``, None if it does not exist."""
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_mtime_ns, st.st_size)


def read_parquet(path: Path) -> pd.DataFrame:
    """A Parquet file as a DataFrame (pyarrow)."""
    return pd.read_parquet(path, engine="pyarrow")


def read_json(path: Path) -> Any:
    """A JSON file (NaN allowed, as Python writes it)."""
    return json.loads(path.read_text(encoding="utf-8"))


def read_pickle(path: Path) -> Any:
    """A pickle of the run (its own files only: a pickle can run code when loaded)."""
    return storage.read_pickle(path)


class FileCache:
    """Files read once per change, shared by the server's threads."""

    def __init__(self) -> None:
        self._entries: dict[tuple[Path, str], FileRead] = {}
        self._lock = threading.Lock()

    def read(self, path: Path, reader: Callable[[Path], Any]) -> FileRead:
        """``reader(path)``, from the cache while the file's stamp is unchanged; a missing
        file gives ``FileRead(None, None, None)``, a damaged one its message."""
        key = (path, getattr(reader, "__qualname__", repr(reader)))
        now = stamp(path)
        if now is None:
            with self._lock:
                self._entries.pop(key, None)
            return FileRead(None, None, None)
        with self._lock:
            cached = self._entries.get(key)
        if cached is not None and cached.stamp == now:
            return cached
        try:
            got = FileRead(reader(path), None, now)
        except Exception as err:  # noqa: BLE001 - any failure to read is shown on the page
            got = FileRead(None, f"{path} cannot be read ({describe(err)})", now)
        with self._lock:
            self._entries[key] = got
        return got
