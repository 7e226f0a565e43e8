"""The run's log file ``DIR/run.log``: library warnings and worker output, not the terminal.

A long run's terminal (or a scheduler's output file) should say how far the run is, not repeat
BoTorch's optimiser warnings. While a study or one of its jobs runs (:func:`run_log`), every
Python warning (BoTorch, gpytorch, linear_operator, NumPy, ...) is appended to ``DIR/run.log``
as one line ``<time> WARNING [<job>] <category>: <message> (<file>:<line>)``; in a worker
process, what is printed (CasADi and IPOPT print through Python's ``sys.stdout``) is appended
as ``OUTPUT`` lines. ``summary.json`` counts the WARNING lines (``warnings``). Several processes
append to the same file; each line is one ``write`` of a file opened for appending.
"""

from __future__ import annotations

import io
import os
import sys
import time
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import TextIO

LOG_NAME = "run.log"
WARNING = "WARNING"


class RunFileWarning(UserWarning):
    """A run file could not be read and an older generation was used; also shown on stderr."""


def log_path(out_dir: str | Path) -> Path:
    """The run's log file, ``DIR/run.log``."""
    return Path(out_dir) / LOG_NAME


def append(out_dir: str | Path, source: str, kind: str, text: str) -> None:
    """Append one line to ``DIR/run.log`` (newlines in ``text`` become `` | ``)."""
    flat = " | ".join(line.rstrip() for line in str(text).splitlines() if line.strip())
    line = f"{time.strftime('%Y-%m-%d %H:%M:%S')} {kind} [{source}] {flat}\n"
    try:
        fd = os.open(log_path(out_dir), os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o666)
    except OSError:  # the directory is gone or read-only: the log is not worth a crash
        return
    try:
        os.write(fd, line.encode("utf-8", "replace"))
    finally:
        os.close(fd)


def count_warnings(out_dir: str | Path) -> int:
    """The number of warnings logged in ``DIR/run.log`` (0 if there is none)."""
    try:
        with log_path(out_dir).open("rb") as fh:
            return sum(1 for line in fh if line.split(b" ", 4)[2:3] == [WARNING.encode()])
    except OSError:
        return 0


class _LineWriter(io.TextIOBase):
    """A text stream whose complete lines go to the run's log as OUTPUT lines."""

    def __init__(self, out_dir: str | Path, source: str) -> None:
        self.out_dir, self.source, self.buf = out_dir, source, ""

    def writable(self) -> bool:
        return True

    def write(self, s: str) -> int:
        self.buf += s
        *lines, self.buf = self.buf.split("\n")
        for line in lines:
            if line.strip():
                append(self.out_dir, self.source, "OUTPUT", line)
        return len(s)

    def flush(self) -> None:
        if self.buf.strip():
            append(self.out_dir, self.source, "OUTPUT", self.buf)
        self.buf = ""


@contextmanager
def run_log(out_dir: str | Path, source: str, capture_output: bool = False) -> Iterator[None]:
    """Route warnings (and with ``capture_output`` stdout / stderr) into ``DIR/run.log``."""

    def show(
        message: Warning | str,
        category: type[Warning],
        filename: str,
        lineno: int,
        file: TextIO | None = None,
        line: str | None = None,
    ) -> None:
        append(out_dir, source, WARNING, f"{category.__name__}: {message} ({filename}:{lineno})")
        if issubclass(category, RunFileWarning):
            print(f"Warning: {message}", file=sys.stderr, flush=True)

    with warnings.catch_warnings():
        warnings.simplefilter("always")  # every occurrence is counted, not the first only
        warnings.filterwarnings("ignore", category=DeprecationWarning)
        warnings.filterwarnings("ignore", category=PendingDeprecationWarning)
        warnings.showwarning = show
        if not capture_output:
            yield
            return
        old = sys.stdout, sys.stderr
        sys.stdout = _LineWriter(out_dir, source)
        sys.stderr = _LineWriter(out_dir, source)
        try:
            yield
        finally:
            for stream in (sys.stdout, sys.stderr):
                stream.flush()
            sys.stdout, sys.stderr = old
