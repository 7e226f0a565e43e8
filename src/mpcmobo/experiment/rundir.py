"""A study's directory and its rules: starting a run, resuming it, extending its budget.

:func:`open_run` is the one owner of these rules (the CLI and :func:`run_study` both go through
it): a new run needs an empty directory and saves every setting to ``config.toml``; a resumed run
uses the saved settings, of which only ``workers``, ``backend`` and a larger ``episodes`` budget
may change. :class:`RunDirectory` reads and writes the typed records of the directory (layout in
:mod:`mpcmobo.experiment.storage`).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import pickle
import shutil
import socket
import warnings
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from mpcmobo import __version__
from mpcmobo.experiment import storage
from mpcmobo.experiment.interrupts import process_alive
from mpcmobo.experiment.logs import RunFileWarning
from mpcmobo.experiment.records import Checkpoint, Reference
from mpcmobo.experiment.settings import (
    Settings,
    SettingsError,
    read_toml,
    settings_from,
    settings_to_toml,
)

T = TypeVar("T")

# what a resumed run may take from the settings it is given (the rest is the saved run's)
RESUME_CHANGES = ("workers", "backend", "episodes")
# the file that names the process of a study while it runs (RunDirectory.running)
RUNNING_FILE = "running.json"


class StudyError(RuntimeError):
    """A study cannot run as asked (e.g. the output directory already holds another run)."""


class ReferenceFailed(StudyError):
    """J* or J_eval(theta0) could not be computed on the plant: a new run ends with nothing
    of it kept (:func:`~mpcmobo.experiment.study.run_study`)."""


class RunFileError(StudyError):
    """A file of a run cannot be read; the message names it and says what to do."""


class RunDirError(StudyError):
    """The directory given cannot take the run asked for: a file, a directory that holds
    another run, is not empty or cannot be written, a missing parent, no run to resume, or a
    budget that would shrink. A mistake in the command, as invalid settings are (the CLI's
    exit code 2); nothing is written."""


class OlderRunError(StudyError):
    """The run was written by an older mpcmobo whose checkpoints this version cannot resume
    (the CLI's exit code 2); its records stay readable."""


# keys an older version wrote to config.toml that this one does not know; dropped when an old
# run's settings are read for its records (plot, evaluate), never on resume
READ_ONLY_DROPS = {"mpc": ("barrier_steps", "barrier_mu0", "barrier_push")}

# settings a run saved before they existed ran without: their value then, where today's default
# differs (the MPC's Newton steps: IPOPT only; identification: none; exploration: no budget)
SAVED_BEFORE = {
    ("mpc", "newton_steps"): 0,
    ("system", "identify"): False,
    ("exploration", "budget"): math.inf,
}


def _saved_before(saved: dict[str, Any]) -> dict[str, Any]:
    """The :data:`SAVED_BEFORE` settings ``saved`` (a run's ``config.toml``) lacks, as
    overrides of :func:`load_settings` (a section that is not a table is left to validation)."""
    return {
        f"{section}__{key}": value
        for (section, key), value in SAVED_BEFORE.items()
        if isinstance(saved.get(section, {}), dict) and key not in saved.get(section, {})
    }


# what reading a damaged pickle or Parquet file can raise (truncated, empty, garbage, wrong type)
READ_ERRORS = (
    OSError,
    EOFError,
    pickle.UnpicklingError,
    ValueError,
    TypeError,
    KeyError,
    AttributeError,
    IndexError,
    ImportError,
)


def read_run_file(path: Path, read: Callable[[Path], T], fix: str) -> T:
    """``read(path)``, or a :class:`RunFileError` naming ``path``, the problem and ``fix``."""
    tail = f"; {fix}" if fix else ""
    try:
        return read(path)
    except READ_ERRORS as err:
        raise RunFileError(f"{path} cannot be read ({_describe(err)}){tail}") from None
    except Exception as err:  # noqa: BLE001 - e.g. pyarrow's errors; reported the same way
        raise RunFileError(f"{path} cannot be read ({_describe(err)}){tail}") from None


def _describe(err: BaseException) -> str:
    text = str(err).strip().splitlines()[0] if str(err).strip() else ""
    if isinstance(err, EOFError) and not text:
        text = "the file is empty or truncated"
    return f"{type(err).__name__}: {text}" if text else type(err).__name__


class RunDirectory:
    """The directory of one study: its settings, reference and job checkpoints."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.config = self.path / "config.toml"
        self.reference_path = self.path / "reference.pkl"
        self.tuner_mark = self.path / "tuner.json"  # written by a Tuner (ask and tell)

    def holds_run(self) -> bool:
        """Whether the directory holds a run (its ``config.toml`` exists)."""
        return self.config.exists()

    def remove_new(self, existed: bool) -> None:
        """Remove what a new run or tuner wrote here before it failed to start: the
        directory's contents (``existed``: it was there, empty, before) or the directory."""
        for item in [*self.path.iterdir()] if existed else [self.path]:
            if item.is_dir():
                shutil.rmtree(item, ignore_errors=True)
            else:
                item.unlink(missing_ok=True)

    def system_file_changed(self) -> bool:
        """Whether the file of the run's system factory (``[system] factory`` of its
        ``config.toml``) was written after its reference: a cheap sign, without building the
        system, that the system may have changed (the full check: ``reference.
        check_run_system``). False for a named system, or where either file is missing."""
        import tomllib

        try:
            config = tomllib.loads(self.config.read_text(encoding="utf-8"))
            factory = str(config["system"]["factory"])
            source = Path(factory.rsplit(":", 1)[0])
            return source.stat().st_mtime_ns > self.reference_path.stat().st_mtime_ns
        except (OSError, ValueError, KeyError, TypeError):
            return False

    @contextlib.contextmanager
    def running(self) -> Iterator[None]:
        """While a study runs in this process: ``running.json`` names the process (its pid and
        host), so that a reader (the dashboard) tells a study in progress from one that was
        killed; removed when the study ends, however it ends (a process killed with
        ``kill -9`` leaves it, naming a process that is gone)."""
        path = self.path / RUNNING_FILE
        self._claim(path)
        try:
            yield
        finally:
            path.unlink(missing_ok=True)

    def _claim(self, path: Path) -> None:
        """Create ``running.json`` naming this process, or refuse (:class:`StudyError`) where it
        names another study's process that runs (or may: on another host); one that names a
        process that is gone (killed) is replaced."""
        mark = json.dumps({"pid": os.getpid(), "host": socket.gethostname()})
        for _ in range(3):
            try:
                with open(path, "x", encoding="utf-8") as f:
                    f.write(mark)
                return
            except FileExistsError:
                if self.study_alive() is False:
                    path.unlink(missing_ok=True)
                    continue
                named = path.read_text(encoding="utf-8", errors="replace").strip()
                raise StudyError(
                    f"{self.path} is being run by another process ({RUNNING_FILE}: {named}): "
                    f"wait for it to end or stop it (Ctrl-C, or kill PID); where that process "
                    f"is gone (another host's), delete {path} and run again"
                ) from None
        raise StudyError(f"{path} cannot be claimed: another process writes it")

    def study_alive(self) -> bool | None:
        """Whether the process of a study runs in the directory: True, False (none is named in
        ``running.json``, or it is gone), None (it ran on another host: cannot tell here)."""
        try:
            named = json.loads((self.path / RUNNING_FILE).read_text(encoding="utf-8"))
            pid, host = int(named["pid"]), str(named["host"])
        except (OSError, ValueError, KeyError, TypeError):
            return False
        if host != socket.gethostname():
            return None
        return process_alive(pid)

    def is_tuner(self) -> bool:
        """Whether the run is a tuner's (ask and tell): its episodes run on a plant outside
        mpcmobo, so ``mpcmobo run --resume`` must not run them."""
        return self.tuner_mark.exists()

    def saved_settings(self, *, for_records: bool = False, **overrides: Any) -> Settings:
        """The run's saved settings (with ``overrides``, see :func:`load_settings`).

        ``for_records``: the settings to read the run's records with (``plot``,
        ``evaluate``): the learners' options are left out and keys an older version saved
        that this one does not know are dropped, so that a run of an older version can still
        be evaluated."""
        if self.path.exists() and not self.path.is_dir():
            raise RunDirError(f"{self.path} is a file, not a run directory")
        if not self.holds_run():
            raise RunDirError(f"nothing to resume: {self.config} does not exist")
        try:
            saved = read_toml(self.config)
            before = _saved_before(saved)
            if for_records:
                saved.pop("learner_options", None)
                for section, keys in READ_ONLY_DROPS.items():
                    for key in keys:
                        saved.get(section, {}).pop(key, None)
            return settings_from(saved, **{**before, **overrides})
        except SettingsError as err:
            if str(err).startswith(str(self.config)):  # the file itself, not an override
                raise SettingsError(
                    f"{err}\n  this file holds the settings of the run in {self.path}: repair "
                    f"it (summary.json has them under 'settings', if the run got that far)"
                ) from None
            raise

    # ------------------------------------------------------------------ opening
    def check_new(self, parents: bool = True) -> None:
        """That a new run can start here: an empty directory, or a new one in a writable
        directory (``parents``: missing parent directories may be created); else a
        :class:`RunDirError` saying why. Nothing is created."""
        path = self.path
        if path.exists():
            if not path.is_dir():
                raise RunDirError(f"{path} is a file; give a new or empty directory")
            if self.holds_run():
                raise RunDirError(
                    f"{path} holds a run; choose a new --out directory, or continue it with "
                    "--resume (--resume --episodes N extends it)"
                )
            if any(path.iterdir()):
                raise RunDirError(f"{path} is not empty; choose a new or empty directory")
            if not os.access(path, os.W_OK | os.X_OK):
                raise RunDirError(f"{path}: the directory is not writable")
            return
        parent = path.parent
        while not parent.exists() and parents and parent != parent.parent:
            parent = parent.parent
        if not parent.exists():
            raise RunDirError(
                f"--out {path}: the parent directory {path.parent} does not exist; create it "
                "first or choose another --out"
            )
        if not parent.is_dir():
            raise RunDirError(f"{path}: {parent} is a file, not a directory")
        if not os.access(parent, os.W_OK | os.X_OK):
            raise RunDirError(f"{path}: cannot create it, {parent} is not writable")

    def create(self, settings: Settings, parents: bool = True) -> Settings:
        """Start a new run here: the directory must be empty or new (:meth:`check_new`);
        every setting is saved. If that fails, nothing created here is left behind."""
        self.check_new(parents)
        resolved = settings.resolved()
        made = []
        for d in reversed([self.path, *self.path.parents]):
            if not d.exists():
                made.append(d)
        try:
            self.path.mkdir(parents=True, exist_ok=True)
            storage.atomic_write_text(self.config, settings_to_toml(resolved))
        except OSError as err:
            for d in reversed(made):
                try:
                    d.rmdir()
                except OSError:
                    break
            raise RunDirError(f"{self.path}: cannot write the run there ({err})") from None
        return resolved

    def check_schema(self) -> None:
        """That every job checkpoint of the run is of this version's schema, else an
        :class:`OlderRunError` naming the version that wrote it and what to do."""
        for path in sorted((self.path / "jobs").glob("*/checkpoint*.pkl")):
            try:
                schema = storage.checkpoint_schema(storage.read_pickle(path))
            except READ_ERRORS:
                continue  # damaged: the checkpoint's own reading reports it
            if schema is not None and schema != storage.CHECKPOINT_SCHEMA:
                made_by = storage.SCHEMA_WRITERS.get(schema, f"checkpoint schema {schema}")
                raise OlderRunError(
                    f"{path}: this run was written by {made_by} (checkpoint schema {schema}); "
                    f"mpcmobo {__version__} resumes only its own checkpoints (schema "
                    f"{storage.CHECKPOINT_SCHEMA}). Its records stay readable: `mpcmobo plot "
                    f"{self.path}` and `mpcmobo evaluate {self.path}`; to go on learning, start a "
                    "new run with the same settings (--config config.toml) in a new directory"
                )

    def reopen(self, settings: Settings | None) -> Settings:
        """The saved settings, with the changes a resumed run may take from ``settings``; a
        larger budget is saved (the settings of the run from now on), a smaller one refused.
        A run written by an older version is refused (:meth:`check_schema`)."""
        if self.holds_run():
            self.check_schema()
        saved = self.saved_settings()
        if settings is None:
            return saved
        if settings.episodes < saved.episodes:
            raise RunDirError(
                f"episodes: the run in {self.path} has a budget of {saved.episodes}; a resumed "
                f"run can be extended, not shortened (got {settings.episodes})"
            )
        changed = saved.model_copy(update={k: getattr(settings, k) for k in RESUME_CHANGES})
        if settings.episodes > saved.episodes:
            storage.atomic_write_text(self.config, settings_to_toml(changed))
        return changed

    # ------------------------------------------------------------------ records
    def reference(self) -> Reference | None:
        """The study-level reference, if it was computed."""
        if not self.reference_path.exists():
            return None
        return read_run_file(
            self.reference_path,
            lambda p: Reference.from_dict(storage.read_pickle(p)),
            (
                f"delete it: the tuner computes it again when it is loaded (`mpcmobo status "
                f"{self.path}`)"
                if self.is_tuner()
                else f"delete it and continue with `mpcmobo run --resume --out {self.path}`, "
                "which computes it again"
            )
            + " (J* and J_eval(theta0); the jobs' records are not affected)",
        )

    def save_reference(self, reference: Reference) -> None:
        """Write ``reference.pkl`` (J*, J_initial, theta0)."""
        storage.write_pickle(self.reference_path, reference.to_dict())

    def checkpoint(self, learner: str, seed: int) -> Checkpoint | None:
        """The job's last checkpoint (None if it has not finished an episode).

        If the latest checkpoint cannot be read, the generation before it is used (one episode
        less, run again on resume) with a :class:`RunFileWarning`; the damaged file is kept
        beside it as ``checkpoint.pkl.damaged``. If neither can be read: :class:`RunFileError`.
        """
        path = storage.checkpoint_path(self.path, learner, seed)
        prev = storage.previous_checkpoint_path(self.path, learner, seed)
        job_dir = path.parent
        fix = (
            f"restore it, or delete {job_dir} to run the job {storage.job_name(learner, seed)} "
            "again from its first episode"
        )
        if path.exists():
            try:
                return _read_checkpoint(path, learner, seed)
            except RunFileError as err:
                if not prev.exists():
                    raise RunFileError(f"{err}; there is no earlier checkpoint; {fix}") from None
                try:
                    ckpt = _read_checkpoint(prev, learner, seed)
                except RunFileError as err2:
                    raise RunFileError(
                        f"{err}; and the previous generation: {err2}; {fix}"
                    ) from None
                damaged = path.with_name(path.name + ".damaged")
                try:  # kept for inspection; the next save starts a new generation
                    os.replace(path, damaged)
                except OSError:
                    damaged = path
                warnings.warn(
                    f"{err}; continuing from the previous checkpoint {prev.name} "
                    f"({len(ckpt.rows)} episodes); the damaged file is kept as {damaged.name}",
                    RunFileWarning,
                    stacklevel=2,
                )
                return ckpt
        if prev.exists():  # replaced at the moment of a crash: the previous generation holds
            return read_run_file(prev, lambda p: _read_checkpoint(p, learner, seed), fix)
        return None

    def save_checkpoint(self, ckpt: Checkpoint) -> None:
        """Write the job's checkpoint; the one it replaces is kept as the previous one."""
        storage.save_checkpoint(self.path, ckpt.learner, ckpt.seed, ckpt.to_dict())

    def incumbents(self, settings: Settings) -> list[tuple[str, int, int, np.ndarray]]:
        """(learner, seed, episodes done, incumbent after the last one) of every job of
        ``settings`` that has run an episode."""
        out = []
        for learner in settings.learners:
            for seed in settings.seeds:
                ckpt = self.checkpoint(learner, seed)
                if ckpt is not None and ckpt.rows:
                    out.append((learner, seed, len(ckpt.rows), ckpt.incumbent))
        return out  # type: ignore[return-value]  # a checkpoint with rows has an incumbent


def open_run(
    out: str | Path, settings: Settings | None, resume: bool
) -> tuple[RunDirectory, Settings]:
    """The run directory ``out`` and the settings of the run in it: a new run (``settings``
    required, the directory empty) or, with ``resume``, the saved run (see
    :meth:`RunDirectory.reopen`)."""
    run_dir = RunDirectory(out)
    if resume:
        return run_dir, run_dir.reopen(settings)
    if settings is None:
        raise StudyError("settings are required for a new study")
    return run_dir, run_dir.create(settings)


def _read_checkpoint(path: Path, learner: str, seed: int) -> Checkpoint:
    """One checkpoint file, checked: it is a checkpoint of a known schema and of this job."""

    def read(p: Path) -> Checkpoint:
        d: Any = storage.read_pickle(p)
        if not isinstance(d, dict):
            raise TypeError(f"holds a {type(d).__name__}, not a checkpoint")
        if storage.checkpoint_schema(d) not in (*storage.SCHEMA_WRITERS, storage.CHECKPOINT_SCHEMA):
            raise ValueError(f"checkpoint schema {storage.checkpoint_schema(d)} is not known")
        if d.get("learner") != learner or int(d.get("seed", -1)) != int(seed):
            raise ValueError(f"it is the checkpoint of {d.get('learner')}-s{d.get('seed')}")
        return Checkpoint.from_dict(d)

    return read_run_file(path, read, "")
