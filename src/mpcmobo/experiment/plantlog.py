"""A plant's logged episode as the tuner reads it: arrays or a table, parsed and checked.

:func:`parse_log` turns what :meth:`~mpcmobo.experiment.tuner.Tuner.tell` is given (arrays, or
one DataFrame with the system's state and input names as columns, the inputs empty in the last
row, optionally ``stage_cost``, ``violation`` and a time column) into a :class:`PlantLog` of
checked shapes and finite numbers; :func:`read_log_file` reads a CSV (its delimiter sniffed) or
Parquet file, :func:`write_log` writes one. What the numbers mean is checked afterwards
(:mod:`mpcmobo.experiment.checks`). Every refusal is a :class:`TunerError` naming the problem.
"""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from mpcmobo.experiment import storage
from mpcmobo.systems.base import System

# a column of one of these names is the log's time (checked for order, not used otherwise)
TIME_COLUMNS = ("time", "t", "timestamp", "time_s", "datetime")
# a number written with a decimal comma: 5,14 or -1,5e-3
DECIMAL_COMMA = r"[-+]?\d*,\d+(?:[eE][-+]?\d+)?"


class TunerError(ValueError):
    """A trial or a log the tuner cannot take; the message says what is wrong. Nothing
    recorded is changed."""


@dataclass
class PlantLog:
    """An episode's log: ``states`` (T+1, nx), ``inputs`` (T, nu), the plant's ``stage_costs``
    and ``violations`` (T,) where it measured them, its ``time`` (T+1,) where it has one, and
    the steps whose input is the controller's fallback (``fallback``: the previous plan's
    input, applied where a solve missed its deadline, as ``mpcmobo connect`` marks it)."""

    states: np.ndarray
    inputs: np.ndarray
    stage_costs: np.ndarray | None = None
    violations: np.ndarray | None = None
    time: np.ndarray | None = None
    fallback: np.ndarray | None = None  # (T,) bool: the input is the controller's fallback

    def frame(self, system: System) -> Any:
        """The log as a table of the tuner's format (what :func:`write_log` writes)."""
        import pandas as pd

        X, U = self.states, self.inputs
        data: dict[str, Any] = {n: X[:, i] for i, n in enumerate(system.state_names)}
        pad = np.full((len(X), U.shape[1]), np.nan)
        pad[: len(U)] = U
        data.update({n: pad[:, i] for i, n in enumerate(system.input_names)})
        for name, arr in (("stage_cost", self.stage_costs), ("violation", self.violations)):
            if arr is not None:
                data[name] = [*np.asarray(arr, float), np.nan]
        if self.fallback is not None:
            data["fallback"] = [*np.asarray(self.fallback, float), np.nan]
        return pd.DataFrame(data)


def numbers(values: Any, name: str) -> np.ndarray:
    """``values`` as an array of floats, or a :class:`TunerError` naming what is not a
    number."""
    try:
        return np.asarray(values, dtype=float)
    except (TypeError, ValueError) as err:
        raise TunerError(f"{name} holds a value that is not a number: {err}") from None


def parse_log(
    system: System, steps: int, states: Any, inputs: Any, stage_costs: Any, violations: Any
) -> PlantLog:
    """The log as a :class:`PlantLog`, checked: shapes, numbers, finite values, inputs within
    their bounds, violations not negative."""
    time = fallback = None
    if hasattr(states, "columns"):  # a DataFrame
        fallback = _fallback(states, steps)
        states, inputs, stage_costs, violations, time = _frame(states, system, steps)
    X, U = _trajectory(system, steps, states, inputs)
    L = _per_step(stage_costs, "stage_costs", steps)
    V = _per_step(violations, "violations", steps)
    return PlantLog(X, U, L, V, time, fallback)


def _fallback(df: Any, steps: int) -> np.ndarray | None:
    """The steps a ``fallback`` column marks 1 (the input is the controller's fallback, the
    previous plan's: what ``mpcmobo connect`` writes where a solve misses its deadline), as a
    (steps,) mask; None without the column."""
    import pandas as pd

    if "fallback" not in df.columns:
        return None
    marked = pd.to_numeric(df["fallback"], errors="coerce").to_numpy(float)[:steps] == 1.0
    return np.concatenate([marked, np.zeros(max(steps - len(marked), 0), bool)])


def _trajectory(system: System, steps: int, states: Any, inputs: Any) -> tuple[np.ndarray, ...]:
    """The states (T+1, nx) and inputs (T, nu) of a log, checked: shapes, finite values,
    inputs within their bounds."""
    s, T = system, steps
    X = numbers(states, "states")
    if inputs is None:
        raise TunerError("the log needs the inputs applied (inputs, or input columns)")
    U = numbers(inputs, "inputs")
    if X.shape != (T + 1, s.nx):
        raise TunerError(
            f"states must be ({T + 1}, {s.nx}): the {T + 1} states of the episode "
            f"({', '.join(s.state_names)}), the last after the last input; got {X.shape}"
        )
    if U.shape != (T, s.nu):
        raise TunerError(
            f"inputs must be ({T}, {s.nu}): the {T} inputs applied "
            f"({', '.join(s.input_names)}); got {U.shape}"
        )
    for name, arr, cols in (("states", X, s.state_names), ("inputs", U, s.input_names)):
        if not np.all(np.isfinite(arr)):
            k, j = (int(i[0]) for i in np.nonzero(~np.isfinite(arr)))
            raise TunerError(
                f"{name} has a value that is not finite at step {k} (row {k} of the log): "
                f"{cols[j]} = {arr[k, j]}"
            )
    outside = (U < s.u_lb - 1e-9 * np.abs(s.u_lb) - 1e-12) | (
        U > s.u_ub + 1e-9 * np.abs(s.u_ub) + 1e-12
    )
    if np.any(outside):
        k, j = (int(v[0]) for v in np.nonzero(outside))
        raise TunerError(
            f"input {s.input_names[j]} = {U[k, j]} at step {k} is outside its bounds "
            f"[{s.u_lb[j]}, {s.u_ub[j]}]: log the inputs actually applied"
        )
    return X, U


# a time step this many times the log's usual one or more is a gap: rows missing there
GAP_RATIO = 1.5


def time_gaps(t: np.ndarray) -> list[int]:
    """The rows of the time column ``t`` after which its step is ``GAP_RATIO`` times the
    usual one (the median of its positive steps) or more: rows are missing there."""
    dt = np.diff(np.asarray(t, float))
    positive = dt[dt > 0]
    if not len(positive):
        return []
    usual = float(np.median(positive))
    return [int(k) for k in np.flatnonzero(dt >= GAP_RATIO * usual)]


def describe_gaps(t: np.ndarray, gaps: Sequence[int]) -> str:
    """Where the time column ``t`` has its ``gaps`` (:func:`time_gaps`), in words: "after row
    17 (the time step to row 18 is 2 times the usual)"."""
    dt = np.diff(np.asarray(t, float))
    usual = float(np.median(dt[dt > 0]))
    return ", ".join(
        f"after row {k} (the time step to row {k + 1} is {dt[k] / usual:.3g} times the usual)"
        for k in gaps
    )


def _per_step(values: Any, name: str, steps: int) -> np.ndarray | None:
    """A per-step column of the log (stage costs, violations), checked: one finite number per
    input, violations not negative; None where the log has none."""
    if values is None:
        return None
    a = numbers(values, name).reshape(-1)
    if a.shape != (steps,):
        raise TunerError(f"{name} must be {steps} numbers, one per input; got {a.shape}")
    if not np.all(np.isfinite(a)):
        k = int(np.flatnonzero(~np.isfinite(a))[0])
        column = name.rstrip("s")  # the log's column: stage_cost, violation
        raise TunerError(
            f"{name} has a value that is not finite at step {k} (row {k} of the log's "
            f"column {column!r}): {a[k]}"
        )
    if name == "violations" and np.any(a < 0):
        k = int(np.flatnonzero(a < 0)[0])
        raise TunerError(f"violations cannot be negative; step {k} has {a[k]}")
    return a


def _frame(df: Any, system: System, steps: int) -> tuple[Any, Any, Any, Any, Any]:
    """States, inputs, stage costs, violations and time from a DataFrame with the system's
    state and input names as columns (the inputs' last row empty); a table whose time column
    shows why it has not the ``steps`` + 1 rows of the episode is refused
    (:func:`_row_count`)."""
    import pandas as pd

    names = (*system.state_names, *system.input_names)
    missing = [c for c in names if c not in df.columns]
    if missing:
        found = [str(c) for c in df.columns]
        hint = ""
        if len(found) == 1 and any(d in found[0] for d in ";\t|"):
            hint = "; its header is one column: is the file delimited by something else?"
        raise TunerError(
            f"the log has no column {missing[0]!r}; it needs the states "
            f"{list(system.state_names)} and the inputs {list(system.input_names)}; its "
            f"columns are {found}{hint}"
        )
    optional = [c for c in ("stage_cost", "violation") if c in df.columns]
    for c in (*names, *optional):
        try:
            pd.to_numeric(df[c])
        except (TypeError, ValueError) as err:
            msg = f"the log's column {c!r} holds a value that is not a number: {err}"
            raise TunerError(msg) from None
    U_all = df[list(system.input_names)].to_numpy(float)
    time = _time(df, names)
    if len(U_all) > 1 and np.all(np.isnan(U_all[0])) and np.all(np.isfinite(U_all[-1])):
        raise TunerError(_inputs_at_the_end(time))
    _row_count(time, U_all, steps)
    X = df[list(system.state_names)].to_numpy(float)
    L = df["stage_cost"].to_numpy(float)[:-1] if "stage_cost" in df.columns else None
    V = df["violation"].to_numpy(float)[:-1] if "violation" in df.columns else None
    return X, U_all[:-1], L, V, time


def _row_count(time: np.ndarray | None, inputs: np.ndarray, steps: int) -> None:
    """A table of other than ``steps`` + 1 rows with a ``time`` column: a :class:`TunerError`
    naming where rows are missing (a time step about twice the usual or more:
    :func:`time_gaps`) or repeated (the same time twice), or, with evenly spaced times and
    inputs on its last row, that the state after the last input is missing; and what to do.
    Nothing where the time does not say (the shape check names the counts)."""
    rows = len(inputs)
    if time is None or rows == steps + 1 or rows < 2:
        return
    counts = (
        f"the episode has {steps + 1} rows (the state before each of its {steps} inputs, and "
        f"the state after the last), the log {rows}"
    )
    if rows < steps + 1 and (gaps := time_gaps(time)):
        raise TunerError(
            f"{counts}: a row is missing {describe_gaps(time, gaps)}; restore it from the "
            "plant's records (the state measured and the input applied at that step) and tell "
            "the log again; an episode with a step missing cannot be learned from (if the row "
            "is lost, run the trial again)"
        )
    if rows == steps and np.all(np.isfinite(inputs[-1])):
        raise TunerError(
            f"{counts}: its time steps evenly and its last row has inputs, so the state after "
            "the last input is missing: add it as the last row (its inputs empty) and tell the "
            "log again"
        )
    repeated = [int(k) + 1 for k in np.flatnonzero(np.diff(time) == 0)]
    if rows > steps + 1 and repeated:
        raise TunerError(
            f"{counts}: its time repeats at row{'s' if len(repeated) > 1 else ''} "
            f"{', '.join(map(str, repeated))} (a row written twice): drop the repeated "
            "row and tell the log again"
        )


def _inputs_at_the_end(time: np.ndarray | None) -> str:
    """What a log whose first row has no inputs and whose last row has them is: its inputs
    logged one row late (a ``time`` column that increases says so), or a reversed log."""
    found = "its first row has no inputs and its last row has them"
    late = (
        "the inputs logged one row late (on the row after the step they were applied at, as "
        "some historians write them): move them up one row, the last row's inputs empty, as "
        "the last row is the state after the last input"
    )
    if time is not None and len(time) > 1 and np.all(np.diff(time) > 0):
        return f"{found}, and its time increases: {late}"
    return (
        f"{found}: either the log is in reverse time order (sort it by time, the episode's "
        f"start first) or it has {late}"
    )


def _time(df: Any, names: tuple[str, ...]) -> np.ndarray | None:
    """The log's time column as numbers (None without one, or one that is not a time); a
    column named as a state or an input is not the time."""
    import pandas as pd

    col = next((c for c in df.columns if str(c).lower() in TIME_COLUMNS and c not in names), None)
    if col is None:
        return None
    try:
        return np.asarray(pd.to_numeric(df[col]), float)
    except (TypeError, ValueError):
        pass
    try:
        return np.asarray(pd.to_datetime(df[col]).astype("int64"), float)
    except (TypeError, ValueError):
        return None


# suffixes of files a log is sometimes saved as that are neither CSV nor Parquet
OTHER_FORMATS = {
    ".json": "a JSON file",
    ".xlsx": "an Excel workbook",
    ".xls": "an Excel workbook",
    ".xlsm": "an Excel workbook",
    ".ods": "a spreadsheet",
    ".pkl": "a pickle",
    ".pickle": "a pickle",
    ".h5": "an HDF5 file",
    ".hdf5": "an HDF5 file",
    ".feather": "a Feather file",
    ".mat": "a MATLAB file",
}


def _existing(path: str | Path) -> Path:
    """``path``, a file that exists, not of a format other than CSV or Parquet that its
    suffix names (:data:`OTHER_FORMATS`; else a :class:`TunerError`)."""
    path = Path(path)
    if not path.exists():
        raise TunerError(f"the log {path} does not exist")
    if path.is_dir():
        raise TunerError(f"the log {path} is a directory, not a CSV or Parquet file")
    other = OTHER_FORMATS.get(path.suffix.lower())
    if other is not None:
        raise TunerError(
            f"the log {path} is {other}: a log is a CSV file (comma, semicolon or tab "
            "separated, a header of the state and input names) or a Parquet file; save it as one"
        )
    return path


def _csv_delimiter(path: Path) -> str:
    """The delimiter of a CSV file (comma, semicolon, tab or bar), sniffed from its start."""
    with path.open(newline="") as fh:
        head = fh.read(4096)
    try:
        return csv.Sniffer().sniff(head, delimiters=",;\t|").delimiter
    except csv.Error:
        return ","


def log_columns(path: str | Path) -> list[str]:
    """The column names of a log file, read from its header alone (no pandas: what a command
    checks before anything heavy is imported); a file that does not exist or cannot be read
    is a :class:`TunerError`."""
    path = _existing(path)
    try:
        if path.suffix == ".parquet":
            import pyarrow.parquet as pq  # type: ignore[import-untyped]  # no stubs

            return [str(n) for n in pq.read_schema(path).names]
        with path.open(newline="") as fh:
            header = next(csv.reader(fh, delimiter=_csv_delimiter(path)), [])
    except Exception as err:  # noqa: BLE001 - any unreadable file is reported the same way
        raise TunerError(f"the log {path} cannot be read: {type(err).__name__}: {err}") from None
    return [name.strip() for name in header]


def _decimal_commas(df: Any) -> bool:
    """Whether a column of ``df`` read as text holds numbers written with a decimal comma
    (``5,14``), as spreadsheets in many locales write a semicolon-separated CSV."""
    for name in df.columns:
        col = df[name]
        if col.dtype.kind in "biufc":
            continue
        text = col.dropna().astype(str).str.strip()
        if len(text) and text.str.fullmatch(DECIMAL_COMMA).all():
            return True
    return False


def read_log_file(path: str | Path) -> Any:
    """A log file as a DataFrame: Parquet, or a CSV whose delimiter (comma, semicolon, tab)
    is sniffed, its numbers with a decimal point or, where the delimiter is not a comma, a
    decimal comma (:func:`_decimal_commas`); a file that does not exist, is empty or cannot be
    read is a :class:`TunerError`."""
    path = _existing(path)
    import pandas as pd  # after the checks that need none: a missing file is refused at once

    try:
        if path.suffix == ".parquet":
            df = pd.read_parquet(path)
        else:
            sep = _csv_delimiter(path)
            df = pd.read_csv(path, sep=sep)
            if sep != "," and _decimal_commas(df):
                df = pd.read_csv(path, sep=sep, decimal=",")
    except Exception as err:  # noqa: BLE001 - any unreadable file is reported the same way
        raise TunerError(f"the log {path} cannot be read: {type(err).__name__}: {err}") from None
    if len(df) == 0:
        raise TunerError(f"the log {path} has no rows")
    return df


def write_log(
    path: str | Path,
    states: np.ndarray,
    inputs: np.ndarray,
    system: System,
    stage_costs: np.ndarray | None = None,
    violations: np.ndarray | None = None,
) -> Path:
    """A logged episode as a CSV or Parquet file of the tuner's format (``mpcmobo tell``)."""
    df = PlantLog(
        np.asarray(states, float), np.asarray(inputs, float), stage_costs, violations
    ).frame(system)
    path = Path(path)
    if path.suffix == ".parquet":
        storage.write_parquet(path, df)
    else:
        df.to_csv(path, index=False)
    return path
