"""One run or tuner directory as the dashboard reads it: its settings, reference, records and
the live checkpoints of jobs that have run episodes since the records were last written.

A study writes ``episodes.parquet`` when it ends (a tuner after every tell), and each job's
checkpoint after every episode: the rows of a job whose checkpoint is newer than the records
are taken from the checkpoint, so a study in progress shows every finished episode. Every file
goes through the :class:`~mpcmobo.dashboard.files.FileCache`; what cannot be read becomes a
message of :attr:`RunSource.messages`, never an exception.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from mpcmobo.dashboard.files import FileCache, describe, read_json, read_parquet, read_pickle
from mpcmobo.dashboard.files import stamp as file_stamp
from mpcmobo.dashboard.jsonable import floats2
from mpcmobo.experiment.build import build_system, identified_parameters
from mpcmobo.experiment.records import Reference
from mpcmobo.experiment.rundir import RUNNING_FILE, RunDirectory
from mpcmobo.experiment.settings import Settings, read_toml
from mpcmobo.experiment.tunerstatus import STATUS_KEYS, kept_unsaid, with_recommendation

__all__ = ["RunSource"]

TRAJECTORY_KEYS = ["learner", "seed", "phase", "episode", "start"]


def _settings(path: Path) -> Settings:
    return RunDirectory(path.parent).saved_settings(for_records=True)


def _reference(path: Path) -> Reference:
    return Reference.from_dict(read_pickle(path))


def _trajectory_index(path: Path) -> tuple[pd.DataFrame, pd.DataFrame]:
    """The trajectories file and its index: one row per stored trajectory."""
    df = read_parquet(path)
    if df.empty:
        return df, pd.DataFrame(columns=TRAJECTORY_KEYS)
    return df, df[TRAJECTORY_KEYS].drop_duplicates().reset_index(drop=True)


class RunSource:
    """The files of one run directory, read through a shared cache."""

    def __init__(
        self, path: str | Path, cache: FileCache, serving: Callable[[Path], bool] | None = None
    ) -> None:
        self.path = Path(path)
        self.dir = RunDirectory(self.path)
        self.cache = cache
        self.serving = serving  # whether a tuner's process (mpcmobo serve) runs
        self.messages: list[str] = []
        self._names: tuple[tuple[int, int] | None, dict[int, list[str]]] | None = None

    # ------------------------------------------------------------------ what changed
    def files(self) -> list[Path]:
        """Every file the page is made of (their stamps tell whether it changed)."""
        fixed = [
            "config.toml",
            "reference.pkl",
            "summary.json",
            "status.json",
            "tuner.json",
            "episodes.parquet",
            "trajectories.parquet",
            RUNNING_FILE,
        ]
        jobs = sorted(self.path.glob("jobs/*/checkpoint.pkl"))
        return [self.path / n for n in fixed] + jobs + sorted(self.path.glob("accepted/*.pkl"))

    def stamp(self) -> tuple[Any, ...]:
        """The stamps of :meth:`files`: equal while nothing on disk changed."""
        return tuple((str(p), file_stamp(p)) for p in self.files())

    # ------------------------------------------------------------------ the files
    def _read(self, name: str, reader: Any) -> Any:
        got = self.cache.read(self.path / name, reader)
        if got.error:
            self.messages.append(got.error)
        return got.value

    def begin(self) -> None:
        """Start a new reading: the messages are those of the files as they are now."""
        self.messages = []
        if not self.path.exists():
            self.messages.append(f"{self.path} no longer exists (moved or deleted)")
        elif not self.path.is_dir():
            self.messages.append(f"{self.path} is not a directory")
        elif not self.dir.holds_run():
            self.messages.append(f"{self.path} does not hold a run yet (no config.toml)")

    def settings(self) -> Settings | None:
        """The run's saved settings (None: no or a damaged ``config.toml``)."""
        return self._read("config.toml", _settings)

    def raw_config(self) -> dict[str, Any]:
        """``config.toml`` as plain data (the learners' options included)."""
        return self._read("config.toml", read_toml) or {}

    def reference(self) -> Reference | None:
        """J*, J_eval(theta0), theta0 and the system's description (None until computed)."""
        return self._read("reference.pkl", _reference)

    def summary(self) -> dict[str, Any] | None:
        """``summary.json`` (None until the records are written)."""
        return self._read("summary.json", read_json)

    def status(self) -> dict[str, Any] | None:
        """A tuner's ``status.json`` (None where it writes none); where it says that a told
        log is being learned from, or the pending trial's log is in ``accepted/``, its
        recommendation as ``mpcmobo status`` makes it: a process learns only where the tuner's
        process runs (``serving``)."""
        st = self._read("status.json", read_json)
        if not isinstance(st, dict) or not STATUS_KEYS <= set(st):
            return st
        kept = kept_unsaid(st, self.path)  # a log kept by a process killed before it said so
        if kept is None and (st.get("learning") is None or self.serving is None):
            return st
        learning = st["learning"] if kept is None else kept
        return with_recommendation(dict(st, learning=learning), self.path, self.serving)

    def study_alive(self) -> bool:
        """Whether the study's process runs (:meth:`~mpcmobo.experiment.rundir.RunDirectory.
        study_alive`; one on another host counts as running); a tuner's trials run on its
        plant, outside any process of ours: True."""
        return self.is_tuner() or self.dir.study_alive() is not False

    def is_tuner(self) -> bool:
        """Whether the directory holds a tuner (ask and tell)."""
        return self.dir.is_tuner()

    def _checkpoints(self, every: bool = False) -> dict[tuple[str, int], dict[str, Any]]:
        """The checkpoints newer than ``episodes.parquet`` (a study in progress; a tuner's
        pending trial), by job; ``every``: all of them (the records cannot be read)."""
        records = None if every else file_stamp(self.path / "episodes.parquet")
        out = {}
        for path in sorted(self.path.glob("jobs/*/checkpoint.pkl")):
            st = file_stamp(path)
            if st is None or (records is not None and st[0] <= records[0]):
                continue
            ckpt = self._read(str(path.relative_to(self.path)), read_pickle)
            if isinstance(ckpt, dict) and "learner" in ckpt and "seed" in ckpt:
                out[(str(ckpt["learner"]), int(ckpt["seed"]))] = ckpt
            elif ckpt is not None:
                self.messages.append(f"{path} is not a checkpoint")
        return out

    def episodes(self) -> tuple[pd.DataFrame, dict[tuple[str, int], dict[str, Any]]]:
        """One row per episode of every job (the records, with the rows of newer checkpoints
        instead of a job's recorded ones; every checkpoint's where the records cannot be
        read) and those checkpoints."""
        df = self._read("episodes.parquet", read_parquet)
        damaged = df is None and (self.path / "episodes.parquet").exists()
        live = self._checkpoints(every=damaged)  # a damaged file: the jobs' rows from them
        parts = [] if df is None or df.empty else [df]
        for (learner, seed), ckpt in live.items():
            rows = ckpt.get("rows") or []
            if parts:
                parts[0] = parts[0][~((parts[0].learner == learner) & (parts[0].seed == seed))]
            if rows:
                parts.append(pd.DataFrame(rows))
        if not parts:
            return pd.DataFrame(columns=["learner", "seed", "episode"]), live
        out = pd.concat(parts, ignore_index=True) if len(parts) > 1 else parts[0]
        return out.sort_values(["learner", "seed", "episode"], kind="stable"), live

    def trajectories(self) -> tuple[pd.DataFrame | None, pd.DataFrame]:
        """``trajectories.parquet`` (None if missing or damaged) and its index."""
        got = self._read("trajectories.parquet", _trajectory_index)
        if got is None:
            return None, pd.DataFrame(columns=TRAJECTORY_KEYS)
        return got

    def identified_names(self, settings: Settings | None, n: int) -> list[str]:
        """The names of the ``n`` identified parameters (the system's identifiable ones or
        ``[system] identify``; ``p0, p1, ...`` where they cannot be told)."""
        st = file_stamp(self.dir.config)
        if self._names is None or self._names[0] != st:
            self._names = (st, {})
        known = self._names[1]
        if n not in known:
            names: list[str] = []
            if settings is not None:
                try:
                    system = build_system(settings)
                    names = list(identified_parameters(settings, system, "identify"))
                except Exception as err:  # noqa: BLE001 - a system that cannot be built here
                    self.messages.append(f"the system cannot be built here ({describe(err)})")
            known[n] = names if len(names) == n else [f"p{i}" for i in range(n)]
        return known[n]

    def trajectory(self, key: dict[str, Any]) -> dict[str, Any] | None:
        """The states and inputs of one stored trajectory (None if it is not stored)."""
        learner, seed = str(key["learner"]), int(key["seed"])
        phase, episode, start = str(key["phase"]), int(key["episode"]), int(key["start"])
        for (lr, sd), ckpt in self._checkpoints().items():
            if (lr, sd) != (learner, seed):
                continue
            for t in ckpt.get("trajectories", []):
                if (t["phase"], int(t["episode"]), int(t["start"])) == (phase, episode, start):
                    x, u = np.asarray(t["x"], float), np.asarray(t["u"], float)
                    return {"x": floats2(x.T), "u": floats2(u.T)}
        df, _ = self.trajectories()
        if df is None or df.empty:
            return None
        hit = (df.learner == learner) & (df.seed == seed) & (df.phase == phase)
        sel = df[hit & (df.episode == episode) & (df.start == start)].sort_values("k")
        if sel.empty:
            return None
        xs = [c for c in sel.columns if c.startswith("x_")]
        us = [c for c in sel.columns if c.startswith("u_")]
        x, u = sel[xs].to_numpy(float), sel[us].to_numpy(float)[:-1]
        return {"x": floats2(x.T), "u": floats2(u.T)}
