"""Ask and tell: tune a plant whose episodes run outside mpcmobo (a DCS, a PLC, a simulator).

A :class:`Tuner` is one job of a study (one learner, one seed) in its own run directory,
driven by the user's loop instead of ``mpcmobo run``: :meth:`Tuner.ask` gives the next
:class:`Trial` (its theta, its controller ``trial.policy(x)``, the exploration noise to add at
every step, and where a simulated study would start it), the episode runs on the plant, and
:meth:`Tuner.tell` takes the logged episode: the MPC is solved again on the logged states
(it is deterministic given x and theta), so its actions, values and sensitivities, the critic
and f1..f4 are what a simulated episode would have had; the stage cost and violation are the
system's where the log has none. A log is checked before it is believed
(:mod:`mpcmobo.experiment.checks`): one it does not believe is quarantined and the trial stays
pending, until a corrected log or ``force=True``; one with a state it is sure is in the wrong
unit (or far outside its box) is refused, ``force`` or not; :meth:`Tuner.retract` takes a told
trial back. Each tell is recorded as ``mpcmobo run`` records an episode
(``episodes.parquet``, ``trajectories.parquet``, ``summary.json``, a checkpoint after every ask
and tell), so :meth:`Tuner.load` continues after a crash, also between ask and tell. Where the
system's plant can be simulated (its true parameters, or a plant of the settings), the
deployed theta is evaluated as in a study (J_eval); on a real plant it is not.
"""

from __future__ import annotations

import contextlib
import functools
import json
import math
import pickle
import time
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from mpcmobo.experiment import checks, storage, tunerstatus
from mpcmobo.experiment.build import build_system, needs_plant
from mpcmobo.experiment.job import Job
from mpcmobo.experiment.loop import SIMULATED_NOTE, EpisodePlan
from mpcmobo.experiment.plantlog import PlantLog, TunerError, parse_log, write_log
from mpcmobo.experiment.records import EpisodeRow, Reference
from mpcmobo.experiment.reference import check_run_system, compute_reference, system_info
from mpcmobo.experiment.rundir import RunDirectory, open_run
from mpcmobo.experiment.settings import (
    Settings,
    load_settings,
    settings_to_toml,
    validate_settings,
)
from mpcmobo.experiment.summary import write_records
from mpcmobo.experiment.tunerfiles import TunerFiles, history_errors, told_twin
from mpcmobo.experiment.usersystem import recorded_system, restore_system, save_system
from mpcmobo.learners.base import Progress
from mpcmobo.learners.switch import REFIT_GROWTH
from mpcmobo.mpc import EpisodeRecord, ParametricMPC, replay
from mpcmobo.rl.objectives import mean_stage_cost
from mpcmobo.systems.base import System
from mpcmobo.systems.registry import is_factory_path

T = TypeVar("T")

__all__ = ["LogQuarantined", "Trial", "Tuner", "TunerError", "write_log"]

# a logged first state within this fraction of x_scale of the trial's x0 started there
START_TOLERANCE = 0.05


class LogQuarantined(TunerError):
    """A log the checks do not believe: kept in ``quarantine/`` with the ``problems`` found;
    the trial stays pending (tell a corrected log, or this one with ``force=True``)."""

    def __init__(self, message: str, problems: list[checks.Problem], path: Path) -> None:
        super().__init__(message)
        self.problems, self.path = problems, path


@dataclass(frozen=True)
class Trial:
    """One episode to run on the plant: its ``id`` (the episode's index), ``theta``, the
    ``noise`` (T, nu) to add to the controller's input at step k (zero where the learner wants a
    noise-free episode), ``steps`` T, and ``x0``, where a simulated study would start it (on a
    real plant, start where the plant is and log it). ``policy(x)`` is the MPC's first input
    with theta at the measured state x, warm-started from the previous call: call it at every
    step, in order."""

    id: int
    theta: np.ndarray
    noise: np.ndarray
    steps: int
    x0: np.ndarray
    theta_names: tuple[str, ...]
    mpc: ParametricMPC = field(repr=False, compare=False)

    def policy(self, x: np.ndarray) -> np.ndarray:
        """The input to apply at ``x`` before the noise: ``pi_theta(x)`` (eq. Policy), or the
        MPC's safe fallback where its solve fails."""
        return self.mpc.solve(x, self.theta, sensitivities=False).action

    def restart(self) -> None:
        """Forget the controller's warm start (a new episode of the same trial)."""
        self.mpc.reset()

    def to_json(self) -> dict[str, Any]:
        """The trial as plain data (what ``mpcmobo ask`` prints)."""
        return {
            "id": self.id,
            "theta": dict(zip(self.theta_names, map(float, self.theta))),
            "steps": self.steps,
            "x0": [float(v) for v in self.x0],
            "noise": np.asarray(self.noise).tolist(),
        }


def _one_writer(method: Callable[..., T]) -> Callable[..., T]:
    """``method`` of a :class:`Tuner` run as the one process that changes the tuner
    (:meth:`Tuner._changing`)."""

    @functools.wraps(method)
    def guarded(self: Tuner, *args: Any, **kwargs: Any) -> T:
        with self._changing():
            return method(self, *args, **kwargs)

    return guarded


class Tuner:
    """One learner tuning a plant by ask and tell, recorded in ``out`` (module docstring).

    ``system``: a system name or factory path (as ``--system``), the settings' ``[system]``
    table as a mapping (``{"name": "cstr", "identify": False}``), or a
    :class:`~mpcmobo.systems.System` built in Python (recorded in ``out`` so that
    :meth:`load` builds it again; its functions must be importable); ``learner``: one of the
    learners; ``config``: a settings file; ``overrides``: settings as in
    :func:`~mpcmobo.experiment.settings.load_settings` (``episodes``, ``start_mode``,
    ``learner_options``, ...). ``out`` must be a new or empty directory; :meth:`load` opens an
    existing one.
    """

    def __init__(
        self,
        system: str | Mapping[str, Any] | System | None = None,
        learner: str = "mobo",
        out: str | Path = "tuning",
        *,
        config: str | Path | None = None,
        seed: int = 0,
        **overrides: Any,
    ) -> None:
        per_job = sorted(k for k in ("learners", "seeds", "workers") if k in overrides)
        if per_job:
            raise TunerError(
                f"a tuner runs one learner with one seed in one process: give learner= and "
                f"seed=, not {', '.join(per_job)}"
            )
        if RunDirectory(out).holds_run():
            raise TunerError(
                f"{out} holds a run already: continue it with Tuner.load({str(out)!r}) "
                f"(mpcmobo ask {out}), or give a new directory"
            )
        if system is None and config is None:
            raise TunerError(
                "a new tuner needs its system: give system= (a name, a factory path "
                "'path/to/file.py:make_system', a [system] table or a System) or config= (a "
                "settings file with a [system] table)"
            )
        saved_system = None
        if isinstance(system, System):
            sys_table, saved_system = {"name": system.name}, recorded_system(system)
        elif isinstance(system, Mapping):
            sys_table = dict(system)
        else:
            sys_table = (
                {} if system is None else {"factory" if is_factory_path(system) else "name": system}
            )
        settings = load_settings(
            config,
            system=sys_table or None,
            learners=[learner],
            seeds=[seed],
            workers=1,
            **overrides,
        )
        existed = Path(out).exists()
        run_dir, settings = open_run(out, settings, resume=False)
        try:
            if saved_system is not None:
                save_system(run_dir.path, saved_system)
            self._open(run_dir, settings, new=True)
            storage.atomic_write_text(
                run_dir.tuner_mark, json.dumps({"learner": learner, "seed": seed}) + "\n"
            )
        except BaseException:  # a system or learner that cannot be built: leave no tuner
            run_dir.remove_new(existed)
            raise

    @classmethod
    def load(
        cls,
        out: str | Path,
        episodes: int | None = None,
        exploration_budget: float | None = None,
    ) -> Tuner:
        """The tuner recorded in ``out``, where it stopped (also between ask and tell);
        ``episodes``: a larger budget of trials from now on; ``exploration_budget``: another
        exploration budget (``[exploration] budget``) from the next trial on, which opens
        exploring again where tuning had stopped (both saved with its settings)."""
        run_dir = RunDirectory(out)
        if not run_dir.holds_run():
            raise TunerError(f"{out} holds no tuner (no config.toml)")
        run_dir.check_schema()
        restore_system(run_dir.path)
        settings = run_dir.saved_settings()
        if not run_dir.is_tuner():  # a study of mpcmobo run, whose episodes it runs itself
            raise TunerError(
                f"{out} holds a study of mpcmobo run ({len(settings.learners)} learner(s), "
                f"{len(settings.seeds)} seed(s)), not a tuner: continue it with mpcmobo run "
                f"--resume --out {out}; its results: mpcmobo evaluate {out}, mpcmobo plot "
                f"{out}, mpcmobo dashboard {out}"
            )
        check_run_system(run_dir)
        if episodes is not None and episodes != settings.episodes:
            if episodes < settings.episodes:
                raise TunerError(
                    f"episodes: the tuner in {out} has a budget of {settings.episodes} trials; "
                    f"it can be extended, not shortened (got {episodes})"
                )
            settings = run_dir.reopen(settings.model_copy(update={"episodes": int(episodes)}))
        priced = _with_exploration_budget(settings, exploration_budget)
        tuner = cls.__new__(cls)
        with TunerFiles(run_dir.path).lock():  # loaded as no other process is changing it
            if priced is not None:
                settings = priced
                storage.atomic_write_text(run_dir.config, settings_to_toml(settings))
            tuner._open(run_dir, settings, new=False)
            with tuner._changing():
                tuner._repair(episodes, repriced=priced is not None)
        return tuner

    def _repair(self, episodes: int | None, repriced: bool = False) -> None:
        """At a load: what a process stopped between its steps left undone (a log accepted
        and not learned from, records behind the checkpoint), and the status of a larger
        budget ``episodes`` or of another exploration budget (``repriced``)."""
        self._learn_accepted()
        if repriced:
            self._plan_again_where_exploring_opens()
        if self._records_behind():  # a tell killed after its checkpoint, before its records
            write_records(self.run_dir.path, self.settings, self.reference)
            self._write_status()
        elif repriced or (episodes is not None and episodes > self.files.status_budget()):
            self._write_status()  # the larger budget, for `mpcmobo status`

    def _plan_again_where_exploring_opens(self) -> None:
        """A pending trial planned while tuning had stopped exploring (the deployed theta
        without noise, the learner not asked; ``mpcmobo tell`` prepares the next trial at
        once) is planned again where another exploration budget opens exploring: the trial
        asked next is the learner's, not one more of the deployed controller."""
        pending = self.job.pending
        if pending is None or not pending.get("converged") or self.job.run.price.converged:
            return
        self.job.pending = None
        self.job.save()

    def _records_behind(self) -> bool:
        """Whether ``status.json`` (written last by a tell) is older than the job's checkpoint:
        a tell was stopped after the learner's state was saved and before the records and the
        status were written from it."""
        ckpt = self._checkpoint_file
        status = self.files.status_path
        if not (ckpt.exists() and status.exists()):
            return ckpt.exists()
        return status.stat().st_mtime_ns < ckpt.stat().st_mtime_ns

    def _open(self, run_dir: RunDirectory, settings: Settings, new: bool) -> None:
        self.run_dir, self.settings = run_dir, settings
        self.learner, self.seed = settings.learners[0], settings.seeds[0]
        self._checkpoint_file = storage.checkpoint_path(run_dir.path, self.learner, self.seed)
        system = build_system(settings, self.learner)  # the learner's: its identify checked
        self.evaluates = system.has_true_plant or needs_plant(settings)
        reference = run_dir.reference()
        if reference is None:
            reference = self._reference(settings)
            run_dir.save_reference(reference)
        self.reference = reference
        J0 = reference.J_initial if math.isfinite(reference.J_initial) else None
        self.job = Job(settings, run_dir, self.learner, self.seed, J0, evaluates=self.evaluates)
        if not new:
            self.job.restore()
        self.system = self.job.run.system
        self._policy_mpc = ParametricMPC(self.system, model="imperfect", **settings.mpc.options())
        self.files = TunerFiles(run_dir.path)
        self._errors: dict = {}  # one-step errors of told logs, per (trial, model)
        self._accepted: dict | None = None  # a log accepted and not learned from yet
        self._writing = getattr(self, "_writing", 0)  # the depth of _changing
        self._seen = self._checkpoint_stamp()  # the checkpoint as this object knows it

    def _checkpoint_stamp(self) -> tuple[int, int, int] | None:
        """The job checkpoint's file identity, time and size (None: none yet): it changes
        whenever a process saves the tuner."""
        try:
            st = self._checkpoint_file.stat()
        except FileNotFoundError:
            return None
        return (st.st_ino, st.st_mtime_ns, st.st_size)

    @contextlib.contextmanager
    def _changing(self) -> Iterator[None]:
        """Change the tuner as its one writer: hold ``tuner.lock``
        (:meth:`~mpcmobo.experiment.tunerfiles.TunerFiles.lock`), and refuse where another
        process saved the tuner since this object loaded or last saved it (its change would
        be lost under this one's): a :class:`TunerError` that says to load it again."""
        with self.files.lock():
            if self._writing == 0 and self._checkpoint_stamp() != self._seen:
                raise TunerError(
                    f"the tuner in {self.run_dir.path} was changed by another process since "
                    "this one loaded it (an ask, a tell or a retract there): load it again "
                    f"(Tuner.load) and repeat; nothing of this process's was written"
                )
            self._writing += 1
            try:
                yield
            finally:
                self._writing -= 1
                if self._writing == 0:
                    self._seen = self._checkpoint_stamp()

    def _reference(self, settings: Settings) -> Reference:
        """J* and J_eval(theta0) where the plant can be simulated; else neither."""
        if self.evaluates:
            return compute_reference(settings)
        system = build_system(settings)
        return Reference(
            J_star=None,
            J_initial=math.nan,
            theta0=system.parameterization.theta0.copy(),
            system=system_info(system),
            J_star_missing="the plant is not simulated: the tuner runs on a real plant",
        )

    # ------------------------------------------------------------------ the loop
    @property
    def deployed(self) -> np.ndarray:
        """The theta deployed now (the learner's incumbent)."""
        return np.asarray(self.job.run.learner.incumbent(), dtype=float)

    @property
    def episodes(self) -> int:
        """Trials told so far."""
        return self.job.run.episode

    @_one_writer
    def ask(self) -> Trial:
        """The next trial (the pending one again if it has not been told; after an
        :meth:`accept`, the learner learns first)."""
        if self._accepted is not None:
            self.learn()
        if self.job.done:
            raise TunerError(
                f"the tuner's budget of {self.settings.episodes} trials is spent; give it a "
                f"larger one to go on: Tuner.load(out, episodes=N), or mpcmobo ask "
                f"{self.run_dir.path} --episodes N"
            )
        if self.job.pending is None:
            plan = self.job.run.plan()
            self.job.pending = plan.to_dict()
            self.job.save()  # the learner's state after the proposal, with the trial
            self._write_status()
        return self._trial(EpisodePlan.from_dict(self.job.pending))

    def _trial(self, plan: EpisodePlan) -> Trial:
        self._policy_mpc.reset()
        return Trial(
            id=plan.episode,
            theta=np.array(plan.theta, float),
            noise=np.array(plan.noise, float),
            steps=self.job.run.steps,
            x0=np.array(plan.x0, float),
            theta_names=tuple(self._policy_mpc.theta_names),
            mpc=self._policy_mpc,
        )

    @_one_writer
    def tell(
        self,
        trial: Trial | int,
        states: Any = None,
        inputs: Any | None = None,
        stage_costs: Any | None = None,
        violations: Any | None = None,
        *,
        force: bool = False,
        progress: Progress | None = None,
    ) -> EpisodeRow:
        """Take the logged episode of ``trial``: ``states`` (T+1, nx), the last the state after
        the last input; ``inputs`` (T, nu), the inputs actually applied; ``stage_costs`` and
        ``violations`` (T,) if the plant measured them. Arrays, or one DataFrame with the
        system's state and input names as columns (inputs empty in the last row) and
        optionally ``stage_cost``, ``violation`` and ``time``. Returns the episode's row.

        The log is checked first (:mod:`mpcmobo.experiment.checks`); one the checks do not
        believe is kept in ``quarantine/`` and :class:`LogQuarantined` names the problems: the
        trial stays pending. ``force=True`` tells it all the same (without ``states``: the
        trial's quarantined log), except a log with a state the checks are sure is in the
        wrong unit or far outside its box: that is a :class:`TunerError` naming the
        conversion, ``force`` or not. A log told with ``force`` despite the model check starts
        that check's baseline: later logs are compared with it and the ones told after it.
        ``progress(what, done, total)`` hears the learner's long work (the twin's tuning,
        :meth:`~mpcmobo.learners.base.Learner.use_progress`).

        A tell is :meth:`accept` then :meth:`learn`; a tell that fails or is interrupted in
        between leaves its trial pending."""
        self.accept(trial, states, inputs, stage_costs, violations, force=force)
        return self.learn(progress=progress)

    @_one_writer
    def accept(
        self,
        trial: Trial | int,
        states: Any = None,
        inputs: Any | None = None,
        stage_costs: Any | None = None,
        violations: Any | None = None,
        *,
        force: bool = False,
    ) -> float:
        """The first half of :meth:`tell` (the same arguments): the log checked, and kept in
        ``accepted/`` until :meth:`learn` learns from it (or, after a crash, the next
        :meth:`load`). Quick: what a tuner's process (``mpcmobo serve``) answers a tell with
        before the learner's long work. Returns the episode's plant cost (its mean stage
        cost)."""
        if self._accepted is not None:
            raise TunerError(
                f"trial {self._accepted['plan']['episode']} is told and being learned from: "
                "ask for the next trial"
            )
        plan, record, mpc_time, log, problems = self._checked(
            _trial_id(trial), states, inputs, stage_costs, violations, force
        )
        entry = {
            "plan": plan.to_dict(),
            "record": record,
            "mpc_time": mpc_time,
            "log": log,
            "problems": problems,
            "force": force,
        }
        self.files.save_accepted(plan.episode, entry)
        self._accepted = entry
        self._write_status()
        return float(mean_stage_cost(record))

    @_one_writer
    def learn(self, *, progress: Progress | None = None) -> EpisodeRow:
        """The second half of :meth:`tell`: the learner learns from the accepted log and the
        episode is recorded; its row. Where that fails (or is interrupted) the trial is pending
        again and nothing of it is recorded."""
        entry = self._accepted
        if entry is None:
            raise TunerError("no told log waits to be learned from: tell a trial first")
        self._accepted = None  # the status written with the record: nothing waits
        learner = self.job.run.learner
        learner.use_progress(progress)
        try:
            row = self._complete(
                EpisodePlan.from_dict(entry["plan"]),
                entry["record"],
                entry["mpc_time"],
                entry["log"],
                entry["problems"],
                entry["force"],
            )
        except BaseException:
            self._write_status()  # the trial is pending again
            raise
        finally:
            self.files.drop_accepted()
            learner.use_progress(None)
            self.job.run.learner.use_progress(None)  # a learner reloaded by an interrupted tell
        return row

    def _learn_accepted(self) -> None:
        """After a crash between :meth:`accept` and :meth:`learn`: the pending trial's
        accepted log learned from now (an accepted log of no pending trial is dropped)."""
        pending = self.job.pending
        entry = None if pending is None else self.files.accepted(int(pending["episode"]))
        if entry is None:
            self.files.drop_accepted()
            return
        self._accepted = entry
        self.learn()

    @property
    def learning(self) -> int | None:
        """The trial whose log is accepted and not learned from yet (None: none)."""
        return None if self._accepted is None else int(self._accepted["plan"]["episode"])

    @property
    def accepted_despite(self) -> list[str]:
        """The checks the accepted log not learned from yet was told despite (``force``),
        sorted; empty: none, or no such log."""
        if self._accepted is None:
            return []
        return sorted({p.check for p in self._accepted["problems"]})

    def _checked(
        self,
        tid: int,
        states: Any,
        inputs: Any | None,
        stage_costs: Any | None,
        violations: Any | None,
        force: bool,
    ) -> tuple[EpisodePlan, EpisodeRecord, float, PlantLog, list[checks.Problem]]:
        """The checks of :meth:`accept`: the plan as the episode started, its record, the MPC's
        time, the parsed log and the problems found (a log they do not believe, without
        ``force``, is quarantined: :class:`LogQuarantined`)."""
        plan = self._pending(tid)
        log = self._parsed(plan, states, inputs, stage_costs, violations, force)
        params, model = self._model()
        since = self._baseline()
        history = history_errors(
            self.files, self.episodes, params, self.system, self._errors, since
        )
        problems, record, mpc_time = checks.review(
            self.system, self.job.run.mpc, plan, log, params, model, history, since > 0
        )
        _refuse_unforceable(tid, problems, self.run_dir.path)
        cycled = self.settings.start_mode == "cycle"
        if cycled and not force:  # a log from another start is refused
            self._check_start(plan, log.states[0], problems)
        elif cycled and not self._at_start(plan, log.states[0]):  # kept with the forced ones
            problems.append(
                checks.Problem(
                    "start",
                    f"the log starts further than {START_TOLERANCE:g} x_scale from the trial's x0",
                )
            )
        if problems and not force:
            path = self.files.quarantine(tid, log, problems, self.system)
            self._write_status()
            raise LogQuarantined(_quarantine_message(tid, problems, path), problems, path)
        # once the log is believed; forced under cycled starts, it started at the trial's x0
        started = plan if cycled else self._started(plan, log.states[0])
        if record is None:  # a log the checks stopped at, told with force
            t0 = time.perf_counter()
            record = replay(self.system, self.job.run.mpc, plan.theta, *_arrays(log))
            mpc_time = time.perf_counter() - t0
        return started, record, mpc_time, log, problems

    def _parsed(
        self,
        plan: EpisodePlan,
        states: Any,
        inputs: Any | None,
        stage_costs: Any | None,
        violations: Any | None,
        force: bool,
    ) -> PlantLog:
        """The told log of the trial ``plan`` parsed (without ``states``, with ``force``: its
        quarantined log); one that repeats a told trial's log is a :class:`TunerError`."""
        tid, steps = plan.episode, self.job.run.steps
        if states is None and force:
            log = self.files.quarantined_log(tid, self.system, steps)
        elif states is None:
            raise TunerError("the log needs the states (T+1 rows), and the inputs applied")
        else:
            log = parse_log(self.system, steps, states, inputs, stage_costs, violations)
        twin = told_twin(self.files, self.episodes, log, self._errors, self._repeatable(plan))
        if twin is not None:
            raise TunerError(
                f"this log is trial {twin}'s, told already (the same states and inputs): tell "
                f"trial {tid}'s own log"
            )
        return log

    def _complete(
        self,
        plan: EpisodePlan,
        record: EpisodeRecord,
        mpc_time: float,
        log: PlantLog,
        problems: list[checks.Problem],
        force: bool,
    ) -> EpisodeRow:
        """The episode of ``plan`` recorded, with what a retract needs to undo it."""
        ckpt = self._checkpoint_file
        snapshot = ckpt.read_bytes() if ckpt.exists() else None  # the state after the ask
        try:
            row = self.job.complete(plan, record, "", mpc_time)
        except BaseException:
            # the learner may have observed the episode in part (an interrupt, an error):
            # back to the last checkpoint, where the trial is pending, so it can be told again
            self._open(self.run_dir, self.settings, new=False)
            raise
        self.job.pending = None
        self.files.save_told(plan.episode, plan.to_dict(), log, snapshot, problems, force)
        self.job.save()
        self.files.release(plan.episode, "accepted (force)" if force else "replaced")
        write_records(self.run_dir.path, self.settings, self.reference)
        self._write_status()
        return row

    @_one_writer
    def retract(self, trial: Trial | int, *, later: bool = False) -> list[int]:
        """Take told trials back: the learner's state becomes what it was before ``trial``
        was told, and ``trial`` is pending again (asked again, it is the same trial). Trials
        told after it were proposed by a learner that had seen it: ``later=True`` retracts
        them with it, else they are a :class:`TunerError`. The retracted records and logs are
        kept in ``retracted/``. Returns the retracted trials' ids."""
        if self._accepted is not None:
            self.learn()
        tid = _trial_id(trial)
        if not 0 <= tid < self.episodes:
            raise TunerError(
                f"trial {tid} has not been told: the told trials are "
                + (f"0 to {self.episodes - 1}" if self.episodes else "none")
            )
        ids = list(range(tid, self.episodes))
        if len(ids) > 1 and not later:
            raise TunerError(
                f"{'trial' if len(ids) == 2 else 'trials'} {checks.describe_steps(ids[1:])} "
                f"{'was' if len(ids) == 2 else 'were'} told after trial {tid}, proposed by a "
                f"learner that had seen it: retract them with it (Tuner.retract({tid}, "
                f"later=True), mpcmobo retract {self.run_dir.path} {tid} --with-later); their "
                "logs are kept"
            )
        found = [self.files.told(k, checkpoint=k == tid) for k in ids]
        entries = [e for e in found if e is not None]
        if len(entries) < len(ids) or entries[0].get("checkpoint") is None:
            raise TunerError(
                f"trial {tid} cannot be retracted: the state before its tell was not kept "
                "(told by an older mpcmobo)"
            )
        rows = [r.to_dict() for r in self.job.rows[tid:]]
        self.files.retract(entries, rows, self.system)
        for q in self.files.quarantined():  # a later trial's plan is gone with its log
            if q > tid:
                self.files.release(q, f"dropped: trial {tid} was retracted")
        before = pickle.loads(entries[0]["checkpoint"])
        for _ in range(2):  # the previous generation is that state too
            storage.save_checkpoint(self.run_dir.path, self.learner, self.seed, before)
        self._open(self.run_dir, self.settings, new=False)
        write_records(self.run_dir.path, self.settings, self.reference)
        self._write_status()
        return ids

    def _repeatable(self, plan: EpisodePlan) -> frozenset[int]:
        """The told trials whose log the pending trial's may repeat: the same theta from the
        same start, where the pending trial runs without noise (a converged tuner's)."""
        if np.any(plan.noise):
            return frozenset()
        return frozenset(
            int(r.episode)
            for r in self.job.rows
            if np.array_equal(r.theta, plan.theta) and np.array_equal(r.x0, plan.x0)
        )

    def _baseline(self) -> int:
        """The first told trial the model check compares a log with: the last one told with
        ``force`` despite that check (the user confirmed it is the plant's, e.g. at a noisier
        sensor: the episodes before it measured another noise), else trial 0."""
        confirmed = [tid for tid, found in self.files.forced().items() if "model" in found]
        return max(confirmed, default=0)

    def _model(self) -> tuple[np.ndarray, str]:
        """The model the logs are checked with: the learner's identified model, else the
        MPC's nominal one; and its name."""
        fit = self.job.run.learner.identification()
        if fit is not None and fit.success:
            return np.asarray(fit.params, float), "identified"
        return np.asarray(self.job.run.mpc.model_params, float), "nominal"

    def _at_start(self, plan: EpisodePlan, x_first: np.ndarray) -> bool:
        """Whether the log starts at the trial's ``x0``: within ``START_TOLERANCE`` x_scale of
        it (a measurement of that start)."""
        scale = np.asarray(self.system.x_scale, float)
        return bool(np.all(np.abs(x_first - plan.x0) <= START_TOLERANCE * scale))

    def _check_start(
        self, plan: EpisodePlan, x_first: np.ndarray, problems: list[checks.Problem]
    ) -> None:
        """Under cycled starts an episode must start at its trial's ``x0`` (:meth:`_at_start`);
        else a :class:`TunerError`, with the ``problems`` the checks found."""
        if self._at_start(plan, x_first):
            return
        scale = np.asarray(self.system.x_scale, float)
        j = int(np.argmax(np.abs(x_first - plan.x0) / scale))
        found = "".join(f"{p.message}; " for p in problems)
        name = self.system.state_names[j]
        unit = checks.start_factor(float(x_first[j]), float(plan.x0[j]))
        named = any(p.check == "range" for p in problems)  # the box check named a unit
        if unit is not None and not named:  # the other checks' findings follow from it
            fix = checks.unit_fix(unit)
            raise TunerError(
                f"the log's {name} looks {checks.looks_off_by(unit)}: a unit error? (its "
                f"first value is the trial's start times {unit:g}, at {x_first[j]:.6g} where "
                f"the trial starts at {plan.x0[j]:.6g}); convert the column ({fix}) and tell "
                "the log again"
            )
        noisy = (  # a state in another unit is no noisy measurement of the start
            "correct the log's units and tell it again"
            if named
            else "where the plant did start there and the first row is a noisy measurement "
            "of it, tell the same log file again with --force (force=True)"
        )
        also = (
            f" The checks also found, which may follow from it: {found.rstrip('; ')}."
            if found
            else ""
        )
        raise TunerError(
            f"trial {plan.episode}'s log is refused (nothing is recorded; the trial stays "
            f"pending): it starts at {name} = {x_first[j]:.6g}, the trial at "
            f"{plan.x0[j]:.6g}: under start_mode = 'cycle' thetas are compared from the same "
            "starts, so an episode must start at its trial's x0 (within "
            f"{START_TOLERANCE:g} x_scale); on a plant that cannot be brought there, use "
            f"start_mode = 'random'; {noisy}.{also}"
        )

    def _started(self, plan: EpisodePlan, x_first: np.ndarray) -> EpisodePlan:
        """The plan as its episode started: the trial's own where the log starts at its
        ``x0`` (:meth:`_at_start`), else re-priced from the logged initial state (random
        starts: a real plant starts where it is)."""
        if self._at_start(plan, x_first):
            return plan
        return self.job.run.restarted(plan, x_first)

    def _pending(self, tid: int) -> EpisodePlan:
        """The pending trial's plan, if ``tid`` is its id."""
        pending = self.job.pending
        if pending is not None and int(pending["episode"]) == tid:
            return EpisodePlan.from_dict(pending)
        if tid < self.job.run.episode:
            raise TunerError(
                f"trial {tid} was told already (the tuner is at trial {self.episodes})"
            )
        if pending is None:
            raise TunerError(f"unknown trial {tid}: no trial is pending; ask for one first")
        raise TunerError(f"unknown trial {tid}: the pending trial is {pending['episode']}")

    # ------------------------------------------------------------------ status
    def status(self) -> dict[str, Any]:
        """What is deployed, on what evidence, what tuning cost and what to do next.

        ``told`` trials of the ``budget``, the ``pending`` one; ``trials``: per told trial its
        ``id``, ``role`` (candidate, verification or deployed), ``start``, ``plant_cost`` (the
        episode's mean stage cost), ``excess_cost`` over the deployed controller (None while
        unknown), ``verdict`` and ``forced`` (the checks its log was told despite, with
        ``force``; :mod:`mpcmobo.experiment.tunerstatus`); ``plant_cost`` and
        ``excess_cost`` summed over them; ``quarantined``: the trials whose log is
        quarantined; ``learning``: the told trial whose log the learner has not learned from
        yet (:meth:`accept`; None: none); ``verifying``: whether a candidate is under
        verification; ``recommendation``: ``action`` (continue or stop) and ``reason``;
        ``exploration``: the exploration budget's account (:meth:`_exploration`); the
        ``deployed`` theta, the trials that ran it and its ``evidence``, how often it changed
        from theta0, its last ``J_eval`` (a simulated plant; None until it is evaluated), and
        with identification the last fit (``identification``: per parameter its nominal
        value, estimate and standard deviation; the RMS scaled one-step errors on held-out
        transitions of the fit and of the nominal model; the transitions fitted)."""
        rows = self.job.rows
        deployed = self.deployed
        ran = [r for r in rows if np.allclose(r.theta, deployed, rtol=0, atol=1e-12)]
        J = [  # the deployed theta's own evaluations
            r.J_eval_incumbent
            for r in rows
            if math.isfinite(r.J_eval_incumbent) and np.array_equal(r.incumbent, deployed)
        ]
        incumbents = [self.job.run.learner.theta0, *(np.asarray(r.incumbent) for r in rows)]
        s = self.settings
        learner = self.job.run.learner
        candidate = learner.verifying()
        trials = tunerstatus.trial_table(
            rows,
            learner.theta0,
            s.start_mode,
            s.n_cycle_starts,
            self.files.forced(),
            candidate,
        )
        verifying = candidate is not None
        pending = None if self.job.pending is None else int(self.job.pending["episode"])
        quarantined = self.files.quarantined()
        costs = [r.mean_stage_cost for r in ran if math.isfinite(r.mean_stage_cost)]
        return {
            "learner": self.learner,
            "told": len(rows),
            "budget": s.episodes,
            "pending": pending,
            "trials": trials,
            "quarantined": quarantined,
            "plant_cost": tunerstatus.cumulative(trials, "plant_cost"),
            "excess_cost": tunerstatus.cumulative(trials, "excess_cost"),
            "recommendation": tunerstatus.recommendation(
                len(rows),
                s.episodes,
                pending,
                quarantined,
                str(self.run_dir.path),
                self.job.run.price.converged_,
                self.learning,
                verifying,
                learns=False,  # a told log waits for learn(): nothing in this process learns
            ),
            "learning": self.learning,
            "verifying": verifying,
            "exploration": self._exploration(rows),
            "deployed": dict(zip(self._policy_mpc.theta_names, map(float, deployed))),
            "deployed_episodes": len(ran),
            "evidence": {
                "episodes": [int(r.episode) for r in ran],
                "mean_plant_cost": float(np.mean(costs)) if costs else None,
            },
            "changes_of_deployed": sum(
                1 for a, b in zip(incumbents, incumbents[1:]) if not np.array_equal(a, b)
            ),
            "J_eval": J[-1] if J else None,
            "J_star": self.reference.J_star,
            "J_initial": None
            if not math.isfinite(self.reference.J_initial)
            else self.reference.J_initial,
            "identification": _identification(self.job.run.learner, self.system),
        }

    def _exploration(self, rows: list[EpisodeRow]) -> dict[str, Any]:
        """The exploration budget's account: the ``budget``, the trials whose candidate it
        ``refused`` (the deployed theta ran), those of them whose candidate the learner learned
        from in simulation (``simulated``), the relative ``model_error`` of its predictions so
        far and its ``ratio_error`` on a candidate's cost over the deployed controller's (the
        budget's bound; :mod:`mpcmobo.experiment.price`; both None before two), and why tuning
        ``converged`` (None: it has not)."""
        price = self.job.run.price
        error, ratio = price.error(), price.ratio_error()
        return {
            "budget": price.budget if price.active else None,
            "refused": [int(r.episode) for r in rows if r.refused],
            "simulated": [int(r.episode) for r in rows if SIMULATED_NOTE in r.refused],
            "model_error": error if math.isfinite(error) else None,
            "ratio_error": ratio if math.isfinite(ratio) else None,
            "converged": price.converged_ or None,
        }

    def _write_status(self) -> None:
        """``status.json`` rewritten (atomically: a dashboard may read it at any time)."""
        self.files.write_status(self.status())


def _identification(learner: Any, system: System) -> dict[str, Any] | None:
    """The learner's last fit of the model, as :meth:`Tuner.status` reports it (None
    without)."""
    fit = learner.identification()
    if fit is None:
        return None
    nominal = dict(zip(system.param_names, system.models["imperfect"]))
    return {
        "parameters": {
            name: {"nominal": float(nominal[name]), "estimate": float(q), "std": float(sd)}
            for name, q, sd in zip(fit.names, fit.estimate, fit.std)
        },
        "holdout_error": fit.holdout_error,
        "nominal_error": fit.nominal_error,
        "transitions": fit.n,
        "refit_growth": REFIT_GROWTH,
    }


def _with_exploration_budget(settings: Settings, budget: float | None) -> Settings | None:
    """``settings`` with the exploration budget ``budget``, checked as the settings check it
    (None: no budget given, or the same)."""
    if budget is None or float(budget) == settings.exploration.budget:
        return None
    data = settings.model_dump()
    data["exploration"]["budget"] = budget
    return validate_settings(data)


def _trial_id(trial: Any) -> int:
    """A trial's id: a :class:`Trial`'s, or an integer."""
    if isinstance(trial, Trial):
        return trial.id
    if isinstance(trial, (int, np.integer)) and not isinstance(trial, bool):
        return int(trial)
    raise TunerError(f"a trial is a Trial or its integer id, not {trial!r}")


def _arrays(log: PlantLog) -> tuple[Any, ...]:
    """A log's arrays as :func:`~mpcmobo.mpc.replay` takes them."""
    return log.states, log.inputs, log.stage_costs, log.violations


def _refuse_unforceable(tid: int, problems: list[checks.Problem], directory: Path) -> None:
    """A :class:`TunerError` where the checks found a problem ``force`` does not accept (a
    state the tool is sure is in the wrong unit, or far outside its box): the log is refused,
    with or without ``force``, nothing of it is kept or recorded, and the trial stays pending."""
    refused = [p for p in problems if not p.forceable]
    if not refused:
        return
    found = "".join(f"\n  - {p.check}: {p.message}" for p in refused)
    raise TunerError(
        f"trial {tid}'s log is refused, nothing of it is recorded; the trial stays pending:"
        f"{found}\nCorrect the log and tell it again (Tuner.tell({tid}, log), mpcmobo tell "
        f"{directory} {tid} LOG)"
    )


def _quarantine_message(tid: int, problems: list[checks.Problem], path: Path) -> str:
    """What a quarantined log is told: the problems, where it is kept, what to do."""
    found = "".join(f"\n  - {p.check}: {p.message}" for p in problems)
    return (
        f"trial {tid}'s log is quarantined, not learned from; the trial stays pending:{found}\n"
        f"The log is kept in {path} (the reasons in {path.with_suffix('.json').name}). Tell "
        f"a corrected log, or accept this one with Tuner.tell({tid}, force=True) (mpcmobo "
        f"tell {path.parent.parent} {tid} --force)"
    )
