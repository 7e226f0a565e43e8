"""What a tuner keeps besides a study's records: told logs, quarantine, retracted trials, status.

Layout in the tuner's directory ``DIR``::

    told/trial-<id>.pkl          a told trial: its plan, its log, the problems the checks found
                                 (told with --force)
    told/trial-<id>.checkpoint.pkl  the job's checkpoint before its tell (what a retract restores)
    accepted/trial-<id>.pkl      a log the checks believed (or --force), not learned from yet:
                                 ``Tuner.learn`` takes it, or the next ``Tuner.load``
    quarantine/trial-<id>.parquet a log the checks did not believe (the trial stays pending)
    quarantine/trial-<id>.json   why, and its status: quarantined, accepted (--force), replaced
    quarantine/trial-<id>-<n>.*  an earlier quarantined log of the trial
    retracted/trial-<id>.parquet a retracted trial's log, and .json: its record and when
    retracted/episodes.parquet   the records of every retracted trial, ``retracted_at`` added
    status.json                  ``Tuner.status()``, rewritten after every ask, tell, retract
    tuner.lock                   held (``flock``) while a process changes the tuner
    trials/<id>/                 a trial as ``mpcmobo ask`` wrote it (trial.json, its controller)
    system.pkl                   a ``System`` given as an object (registered again on load)
    system-modules.json          where the modules of that System's functions are

Every file is written atomically (:mod:`mpcmobo.experiment.storage`).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from mpcmobo.experiment import storage
from mpcmobo.experiment.checks import Problem
from mpcmobo.experiment.plantlog import PlantLog, TunerError, parse_log
from mpcmobo.systems.base import System

QUARANTINED = "quarantined"
# the file a process holds while it changes the tuner (TunerFiles.lock), and how long another
# process waits for it
LOCK_FILE = "tuner.lock"
LOCK_WAIT_S = 600.0


# per lock file: this process's hold of it (its descriptor and depth) and its threads' lock
_HELD: dict[Path, list[Any]] = {}
_HELD_GUARD = threading.Lock()


@contextlib.contextmanager
def writer_lock(path: Path, timeout: float = LOCK_WAIT_S) -> Iterator[None]:
    """Hold the lock file ``path`` (an exclusive ``flock``, which the system releases when the
    process ends, however it ends) while a process changes the tuner; reentrant in a process
    (a tell holds it through its accept and its learning), one thread at a time. A lock that
    another process holds is waited for up to ``timeout`` seconds, then a
    :class:`TunerError`. Where the system has no ``flock`` (Windows), only the threads of this
    process are kept apart."""
    path = path.resolve()
    with _HELD_GUARD:
        held = _HELD.setdefault(path, [None, 0, threading.RLock()])
    with held[2]:
        if held[1] == 0:
            held[0] = _acquire(path, timeout)
        held[1] += 1
        try:
            yield
        finally:
            held[1] -= 1
            if held[1] == 0 and held[0] is not None:
                os.close(held[0])  # releases the lock
                held[0] = None


def _acquire(path: Path, timeout: float) -> int | None:
    """The descriptor of ``path`` with its exclusive ``flock`` taken (None: no ``flock``)."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not on POSIX
        return None
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
    deadline, said = time.monotonic() + timeout, False
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            break
        except BlockingIOError:
            holder = f" (process {_holder(path)})"
            if time.monotonic() > deadline:
                os.close(fd)
                raise TunerError(
                    f"another process{holder} has been changing the tuner in {path.parent} "
                    f"for {timeout:.0f} s (a tell, an ask or a retract): try again when it is "
                    "done"
                ) from None
            if not said:
                print(
                    f"waiting for another process{holder} that changes the tuner in "
                    f"{path.parent} (a tell, an ask or a retract)",
                    file=sys.stderr,
                    flush=True,
                )
                said = True
            time.sleep(0.05)
    os.ftruncate(fd, 0)
    os.write(fd, f"{os.getpid()}\n".encode())
    return fd


def held_elsewhere(path: Path) -> bool:
    """Whether another process holds the lock file ``path`` now (changes the tuner: a tell
    under way); False where the file does not exist or the system has no ``flock``."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not on POSIX
        return False
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return False
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        return True
    finally:
        os.close(fd)  # releases a lock taken here
    return False


def _holder(path: Path) -> str:
    """The process that holds the lock file ``path`` as it wrote itself there ("?": unknown)."""
    try:
        return path.read_text(encoding="ascii").strip() or "?"
    except (OSError, ValueError):
        return "?"


def _now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


class TunerFiles:
    """The tuner files of the directory ``path`` (module docstring)."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.told_dir = self.path / "told"
        self.accepted_dir = self.path / "accepted"
        self.quarantine_dir = self.path / "quarantine"
        self.retracted_dir = self.path / "retracted"
        self.status_path = self.path / "status.json"
        self._forced: dict[str, tuple[int, list[str]]] = {}  # told file: (mtime, checks)

    # ------------------------------------------------------------------ one writer
    def lock(self, timeout: float = LOCK_WAIT_S) -> contextlib.AbstractContextManager[None]:
        """Held while this process changes the tuner (:func:`writer_lock`)."""
        return writer_lock(self.path / LOCK_FILE, timeout)

    # ------------------------------------------------------------------ told trials
    def save_told(
        self,
        tid: int,
        plan: dict,
        log: PlantLog,
        snapshot: bytes | None,
        problems: list[Problem],
        forced: bool,
    ) -> None:
        """Keep a told trial: its plan, log, findings and the checkpoint before its tell (in
        a file of its own, read only by a retract)."""
        if snapshot is not None:
            storage.atomic_write_bytes(self.told_dir / f"trial-{tid}.checkpoint.pkl", snapshot)
        storage.write_pickle(
            self.told_dir / f"trial-{tid}.pkl",
            {
                "trial": tid,
                "plan": plan,
                "log": log,
                "problems": [p.to_dict() for p in problems],
                "forced": forced,
                "told_at": _now(),
            },
        )

    def told(self, tid: int, checkpoint: bool = False) -> dict | None:
        """A told trial's entry (None: not kept, e.g. told by an older version); with
        ``checkpoint``, also the job's checkpoint before its tell (bytes; None if not kept)."""
        path = self.told_dir / f"trial-{tid}.pkl"
        if not path.exists():
            return None
        try:
            entry: dict = storage.read_pickle(path)
        except Exception:  # noqa: BLE001 - a damaged entry is as good as none
            return None
        if checkpoint:
            snap = self.told_dir / f"trial-{tid}.checkpoint.pkl"
            entry["checkpoint"] = snap.read_bytes() if snap.exists() else None
        return entry

    def forced(self) -> dict[int, list[str]]:
        """Per told trial whose log was told with ``--force`` despite problems, the checks
        that found them. Each told entry is read once (``status`` asks after every ask and
        tell), again only when its file changes."""
        out = {}
        for path in self.told_dir.glob("trial-*.pkl"):
            if path.name.endswith(".checkpoint.pkl"):
                continue
            tid, stamp = int(path.stem.split("-")[1]), path.stat().st_mtime_ns
            cached = self._forced.get(path.name)
            if cached is None or cached[0] != stamp:
                entry = self.told(tid) or {}
                found = entry.get("problems") if entry.get("forced") else None
                cached = (stamp, sorted({p["check"] for p in found or []}))
                self._forced[path.name] = cached
            if cached[1]:
                out[tid] = cached[1]
        return out

    # ------------------------------------------------------------------ accepted logs
    def save_accepted(self, tid: int, entry: dict) -> None:
        """Keep trial ``tid``'s accepted log (``entry``: what ``Tuner.learn`` needs) until the
        learner has learned from it."""
        storage.write_pickle(self.accepted_dir / f"trial-{tid}.pkl", dict(entry, trial=tid))

    def accepted(self, tid: int) -> dict | None:
        """Trial ``tid``'s accepted log not learned from yet (None: there is none)."""
        path = self.accepted_dir / f"trial-{tid}.pkl"
        if not path.exists():
            return None
        entry: dict = storage.read_pickle(path)
        return entry

    def accepted_logs(self) -> list[Path]:
        """The files of the accepted logs not learned from yet (at most the pending trial's)."""
        return sorted(self.accepted_dir.glob("trial-*.pkl"))

    def drop_accepted(self) -> None:
        """No accepted log waits any more (learned from, or its learning failed)."""
        for path in self.accepted_logs():
            path.unlink(missing_ok=True)

    # ------------------------------------------------------------------ quarantine
    def quarantine(self, tid: int, log: PlantLog, problems: list[Problem], system: System) -> Path:
        """Keep a log the checks did not believe, with the reasons; its path. A log the trial
        had in quarantine before is kept as ``trial-<id>-<n>``, marked replaced."""
        path = self.quarantine_dir / f"trial-{tid}.parquet"
        kept = _set_aside(self.quarantine_dir, tid)
        if kept is not None:
            entry = storage.read_json(kept)
            if entry.get("status") == QUARANTINED:
                entry.update(status="replaced by a later log", released_at=_now())
                storage.write_json(kept, entry)
        storage.write_parquet(path, log.frame(system))
        storage.write_json(
            path.with_suffix(".json"),
            {
                "trial": tid,
                "status": QUARANTINED,
                "quarantined_at": _now(),
                "problems": [p.to_dict() for p in problems],
                "log": path.name,
            },
        )
        return path

    def quarantined(self) -> list[int]:
        """The trials whose last log is quarantined (not accepted or replaced since)."""
        out = []
        for path in sorted(self.quarantine_dir.glob("trial-*.json")):
            try:
                entry = storage.read_json(path)
            except (OSError, ValueError):
                continue
            if entry.get("status") == QUARANTINED:
                out.append(int(entry["trial"]))
        return sorted(set(out))

    def quarantined_log(self, tid: int, system: System, steps: int) -> PlantLog:
        """The quarantined log of trial ``tid`` (what ``tell --force`` without a log takes)."""
        path = self.quarantine_dir / f"trial-{tid}.parquet"
        if tid not in self.quarantined() or not path.exists():
            raise TunerError(
                f"trial {tid} has no quarantined log: give the log to tell (--force accepts a "
                "log the checks would quarantine)"
            )
        import pandas as pd

        return parse_log(system, steps, pd.read_parquet(path), None, None, None)

    def release(self, tid: int, status: str) -> None:
        """A quarantined log of trial ``tid`` is no longer pending: ``status`` says why."""
        path = self.quarantine_dir / f"trial-{tid}.json"
        if not path.exists():
            return
        entry = storage.read_json(path)
        if entry.get("status") == QUARANTINED:
            entry.update(status=status, released_at=_now())
            storage.write_json(path, entry)

    # ------------------------------------------------------------------ retracted trials
    def retracted_record(self, tid: int) -> Path | None:
        """The file of trial ``tid``'s last retracted record (None: it was not retracted)."""
        path = self.retracted_dir / f"trial-{tid}.json"
        return path if path.is_file() else None

    def retract(self, entries: list[dict], rows: list[dict], system: System) -> None:
        """Keep the told trials ``entries`` (with their ``rows``) in ``retracted/`` and drop
        them from ``told/``. A trial retracted before keeps that log as ``trial-<id>-<n>``."""
        import pandas as pd

        at = _now()
        for entry, row in zip(entries, rows, strict=True):
            tid = int(entry["trial"])
            log: PlantLog = entry["log"]
            _set_aside(self.retracted_dir, tid)
            path = self.retracted_dir / f"trial-{tid}.parquet"
            storage.write_parquet(path, log.frame(system))
            storage.write_json(
                path.with_suffix(".json"),
                {
                    "trial": tid,
                    "retracted_at": at,
                    "told_at": entry.get("told_at"),
                    "problems": entry.get("problems", []),
                    "forced": entry.get("forced", False),
                    "record": row,
                    "log": path.name,
                },
            )
        table = self.retracted_dir / "episodes.parquet"
        new = pd.DataFrame([dict(r, retracted_at=at) for r in rows])
        if table.exists():
            new = pd.concat([pd.read_parquet(table), new], ignore_index=True)
        storage.write_parquet(table, new)
        for entry in entries:
            tid = int(entry["trial"])
            (self.told_dir / f"trial-{tid}.pkl").unlink(missing_ok=True)
            (self.told_dir / f"trial-{tid}.checkpoint.pkl").unlink(missing_ok=True)
        first = min(int(e["trial"]) for e in entries)
        for path in (self.path / "trials").glob("*"):  # proposed after the first: gone with it
            if path.name.isdigit() and int(path.name) > first:
                shutil.rmtree(path, ignore_errors=True)

    # ------------------------------------------------------------------ status
    def status_budget(self) -> int:
        """The budget ``status.json`` says (0 without one)."""
        try:
            return int(storage.read_json(self.status_path)["budget"])
        except (OSError, ValueError, KeyError, TypeError):
            return 0

    def write_status(self, status: dict[str, Any]) -> None:
        """Write ``status.json`` atomically (another program may read it at any time)."""
        storage.write_json(self.status_path, status)


def history_errors(
    files: TunerFiles,
    told: int,
    params: np.ndarray,
    system: System,
    cache: dict,
    since: int = 0,
) -> list[float]:
    """The one-step errors (:func:`~mpcmobo.experiment.checks.episode_error`) under the model
    ``params`` of the ``told`` trials kept, from trial ``since`` on; ``cache`` keeps their logs
    (by trial) and errors (by trial and params) for the tuner's next tell."""
    from mpcmobo.experiment.checks import episode_error

    out = []
    key_p = np.asarray(params, float).tobytes()
    for tid in range(since, told):
        key = (tid, key_p)
        if key not in cache:
            if tid not in cache:
                entry = files.told(tid)
                cache[tid] = None if entry is None else entry["log"]
            log: PlantLog | None = cache[tid]
            if log is None:
                continue
            cache[key] = episode_error(system, log.states, log.inputs, params)
        out.append(cache[key])
    return out


def told_twin(
    files: TunerFiles, told: int, log: PlantLog, cache: dict, same: frozenset[int] = frozenset()
) -> int | None:
    """The told trial whose log ``log`` repeats (the same states and inputs), if one does;
    ``cache`` as :func:`history_errors`'s; ``same``: the told trials that may repeat it (the
    same theta from the same start, and the trial told now without noise: a noise-free plant
    repeats such an episode exactly, and the input check holds it to its controller)."""
    for tid in range(told):
        if tid in same:
            continue
        if tid not in cache:
            entry = files.told(tid)
            cache[tid] = None if entry is None else entry["log"]
        kept: PlantLog | None = cache[tid]
        if (
            kept is not None
            and np.array_equal(kept.states, log.states)
            and np.array_equal(kept.inputs, log.inputs)
        ):
            return tid
    return None


def _set_aside(directory: Path, tid: int) -> Path | None:
    """The log and JSON ``directory`` keeps of trial ``tid`` moved aside to ``trial-<id>-<n>``
    (``n``: 1 for the first kept so), to make room for its next one; the moved JSON (None:
    ``directory`` kept none)."""
    current = directory / f"trial-{tid}.json"
    if not current.exists():
        return None
    n = len(list(directory.glob(f"trial-{tid}-*.json"))) + 1
    kept = directory / f"trial-{tid}-{n}.parquet"
    if current.with_suffix(".parquet").exists():
        os.replace(current.with_suffix(".parquet"), kept)
    storage.write_json(kept.with_suffix(".json"), dict(storage.read_json(current), log=kept.name))
    current.unlink()
    return kept.with_suffix(".json")
