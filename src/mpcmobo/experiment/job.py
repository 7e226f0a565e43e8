"""One job of a study: a learner on a seed, run episode by episode, resumable exactly.

A :class:`Job` builds its own system, MPC (eq. V0), learner and evaluator (no CasADi object
crosses a process boundary); :meth:`Job.restore` continues from its checkpoint, :meth:`Job.step`
runs one episode and :meth:`Job.save` writes its :class:`Checkpoint`. What a job records follows
one :class:`EvaluationSchedule`, also when a run's budget is extended. :func:`run_job` runs a job
in the study's process or in a worker: checkpointing, progress and the watch for an orphaned
worker hang on the job's episodes (:meth:`Job.episodes`), outside the learning loop.
"""

from __future__ import annotations

import math
import os
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch
from threadpoolctl import threadpool_limits

from mpcmobo.experiment import interrupts, storage
from mpcmobo.experiment.build import build_plant, build_system, identified_parameters, needs_plant
from mpcmobo.experiment.evaluation import make_evaluator, mean_cost
from mpcmobo.experiment.logs import run_log
from mpcmobo.experiment.loop import EPISODE_FAILURES, EpisodePlan, LearningRun
from mpcmobo.experiment.price import ExplorationPrice
from mpcmobo.experiment.records import Checkpoint, EpisodeRow, Trajectory
from mpcmobo.experiment.rundir import RunDirectory, RunFileError
from mpcmobo.experiment.settings import Settings, validate_settings
from mpcmobo.identify import ModelFit
from mpcmobo.learners import Learner, Starts, make_learner
from mpcmobo.mpc import EpisodeRecord, ParametricMPC
from mpcmobo.systems.base import System
from mpcmobo.systems.registry import register_system

Progress = Callable[[dict], None]


class EvaluationSchedule:
    """When a job evaluates its incumbent and which of its episodes it stores.

    The incumbent's J_eval is computed at episode 0, at the last episode of the budget, and
    whenever the incumbent differs from the last evaluated one and at least ``eval_every``
    episodes have passed since that evaluation (``J_eval_incumbent`` is NaN in the other rows).
    The last episode also stores the final incumbent's evaluation episodes ("final"); a learning
    episode's states and inputs are stored every ``trajectory_every`` episodes and at the last.
    """

    def __init__(self, episodes: int, eval_every: int, trajectory_every: int) -> None:
        self.last = episodes - 1
        self.eval_every = eval_every
        self.trajectory_every = trajectory_every
        self.theta: np.ndarray | None = None  # the last evaluated incumbent
        self.episode: int | None = None  # and its episode

    @classmethod
    def from_settings(cls, settings: Settings) -> EvaluationSchedule:
        """The schedule of a study's settings (episodes, ``eval_every``, ``trajectory_every``)."""
        return cls(
            settings.episodes, settings.evaluation.eval_every, settings.records.trajectory_every
        )

    def step(self, episode: int, incumbent: np.ndarray) -> bool:
        """Whether the incumbent after ``episode`` is evaluated (then it is the last evaluated)."""
        due = episode in (0, self.last) or (
            (self.theta is None or not np.array_equal(self.theta, incumbent))
            and (self.episode is None or episode - self.episode >= self.eval_every)
        )
        if due:
            self.theta, self.episode = incumbent.copy(), episode
        return due

    def keeps_learning(self, episode: int) -> bool:
        """Whether the learning episode's trajectory is stored."""
        return episode % self.trajectory_every == 0 or episode == self.last

    def state_dict(self) -> dict:
        """The checkpoint's ``eval_state``: empty before the first evaluation."""
        return {} if self.theta is None else {"theta": self.theta, "episode": self.episode}

    def load_state_dict(self, state: dict) -> None:
        """Restore the last evaluated incumbent and its episode."""
        theta = state.get("theta")
        self.theta = None if theta is None else np.asarray(theta, dtype=float)
        self.episode = state.get("episode")


class Job:
    """The job (learner, seed) of a study with ``settings``, recorded in ``run_dir``.

    ``J_initial``: J_eval(theta0) of the study's reference, so that it is not recomputed.
    """

    def __init__(
        self,
        settings: Settings,
        run_dir: RunDirectory,
        learner: str,
        seed: int,
        J_initial: float | None = None,
        *,
        evaluates: bool = True,
    ) -> None:
        self.settings, self.run_dir = settings, run_dir
        self.evaluates = evaluates  # False: a plant that cannot be simulated (no J_eval)
        self.learner, self.seed = learner, seed
        system = build_system(settings, learner)  # theta with the identified parameters, if any
        plant = build_plant(settings, system) if needs_plant(settings) else None
        self.run = _learning_run(settings, system, learner, seed, plant)
        self.evaluator = make_evaluator(settings, system, plant)
        # an interrupt during an MPC solve stops the job when the solve returns, never fails it
        interrupts.guard_solves(self.run.mpc)
        if evaluates:
            interrupts.guard_solves(self.evaluator.mpc("imperfect"))
        if J_initial is not None and evaluates:
            self.evaluator.remember(self.run.mpc.theta0, J_initial)
        self.schedule = EvaluationSchedule.from_settings(settings)
        self.rows: list[EpisodeRow] = []
        self.trajectories: list[Trajectory] = []
        self.wall_time_s = 0.0
        self.pending: dict | None = None  # an episode planned and not yet completed (Tuner)

    @property
    def done(self) -> bool:
        """Whether the job has run its whole budget of episodes."""
        return self.run.episode >= self.settings.episodes

    # ------------------------------------------------------------------ restore / save
    def restore(self) -> None:
        """Continue from the job's checkpoint, if any; a checkpoint of a smaller budget is
        extended to this one (:meth:`_extend`)."""
        ckpt = self.run_dir.checkpoint(self.learner, self.seed)
        if ckpt is None:
            return
        if ckpt.schema != storage.CHECKPOINT_SCHEMA:
            self.run_dir.check_schema()  # raises OlderRunError, naming the version
        path = storage.checkpoint_path(self.run_dir.path, self.learner, self.seed)
        fix = f"delete {path.parent} to run this job again from its first episode"
        try:
            self.run.load_state_dict(ckpt.state)
        except (KeyError, TypeError, ValueError, AttributeError, IndexError) as err:
            raise RunFileError(
                f"{path}: the job's state cannot be restored ({err}); {fix}"
            ) from None
        self.rows, self.trajectories = ckpt.rows, ckpt.trajectories
        self.wall_time_s = ckpt.wall_time_s
        self.pending = ckpt.pending
        if len(self.rows) != self.run.episode:
            raise RunFileError(f"{path} is inconsistent (rows and state differ); {fix}")
        if ckpt.episodes < self.settings.episodes:
            self._extend()
        else:
            self.schedule.load_state_dict(ckpt.eval_state)

    def _extend(self) -> None:
        """Undo what only the end of the old budget recorded, so that the records equal those
        of a run started with this budget: the schedule is replayed over the rows; the old last
        episode keeps its evaluation only if the schedule makes it anyway, and loses its "final"
        trajectories and its learning trajectory if that was off the schedule. Without a row (a
        tuner whose first trial is pending) there is nothing to undo."""
        if not self.rows:
            return
        *before, end = self.rows
        for row in before:
            self.schedule.step(row.episode, np.asarray(row.incumbent, dtype=float))
        if not self.schedule.step(end.episode, np.asarray(end.incumbent, dtype=float)):
            end.J_eval_incumbent = math.nan
        self.trajectories = [
            t
            for t in self.trajectories
            if t.episode != end.episode
            or (t.phase == "learning" and self.schedule.keeps_learning(t.episode))
        ]

    def checkpoint(self) -> Checkpoint:
        """The job's state and records as a :class:`Checkpoint`."""
        return Checkpoint(
            learner=self.learner,
            seed=self.seed,
            state=self.run.state_dict(),
            rows=self.rows,
            trajectories=self.trajectories,
            eval_state=self.schedule.state_dict(),
            wall_time_s=self.wall_time_s,
            episodes=self.settings.episodes,
            done=self.done,
            pending=self.pending,
        )

    def save(self) -> None:
        """Write the job's checkpoint (atomically, never cut by an interrupt)."""
        with interrupts.deferred():  # a checkpoint is written whole
            self.run_dir.save_checkpoint(self.checkpoint())

    # ------------------------------------------------------------------ episodes
    def step(self) -> EpisodeRow:
        """Run the next episode, evaluate its incumbent and store its trajectories as the
        schedule says; return its row.

        An interrupt (:class:`~mpcmobo.experiment.interrupts.Interrupted`) during the episode
        or its evaluation discards the episode: nothing of it is recorded, and a resumed job
        runs it again from the last checkpoint."""
        interrupts.check()
        t_start = time.perf_counter()
        out, record = self.run.run_episode()
        return self._recorded(out, record, t_start)

    def complete(
        self,
        plan: EpisodePlan,
        record: EpisodeRecord | None,
        error: str = "",
        mpc_time: float = 0.0,
    ) -> EpisodeRow:
        """Complete the episode of ``plan`` (from :meth:`LearningRun.plan`) that ran elsewhere,
        from its ``record``, as :meth:`step` completes the episodes it runs."""
        t_start = time.perf_counter()
        out, record = self.run.finish(plan, record, error, mpc_time)
        return self._recorded(out, record, t_start)

    def _recorded(self, out: dict, record: EpisodeRecord | None, t_start: float) -> EpisodeRow:
        """The episode's row, evaluated and stored as the schedule says."""
        interrupts.check()
        row = EpisodeRow.from_dict(out)
        t_eval = time.perf_counter()
        row.J_eval_incumbent, failure = self._evaluate(
            row.episode, np.asarray(row.incumbent, dtype=float)
        )
        if failure:
            row.error = f"{row.error}; {failure}" if row.error else failure
        row.eval_time_s = time.perf_counter() - t_eval
        interrupts.check()  # nothing of an interrupted evaluation is kept
        if record is not None and self.schedule.keeps_learning(row.episode):
            self.trajectories.append(Trajectory("learning", row.episode, 0, record.x, record.u))
        self.rows.append(row)
        self.wall_time_s += time.perf_counter() - t_start
        return row

    def _final_episodes(self, episode: int, incumbent: np.ndarray) -> list[Trajectory]:
        """The final incumbent's evaluation episodes: theta0's are the reference's, whose cost
        is every job's J_eval of theta0 (solved again, another local minimum from a hot start
        would draw another closed loop than that J_eval's); another theta's simulated now, its
        J_eval theirs."""
        theta0 = np.array_equal(incumbent, self.run.mpc.theta0)
        reference = (
            self.run_dir.reference() if theta0 and self.evaluator.is_cached(incumbent) else None
        )
        trajectories = [] if reference is None else reference.trajectories
        initial = [t for t in trajectories if t.phase == "initial"]
        if initial:
            return [Trajectory("final", episode, t.start, t.x.copy(), t.u.copy()) for t in initial]
        eps = self.evaluator.episodes(incumbent)
        if not self.evaluator.is_cached(incumbent):
            self.evaluator.remember(incumbent, mean_cost(eps))
        return [Trajectory("final", episode, i, r.x.copy(), r.u.copy()) for i, r in enumerate(eps)]

    def _evaluate(self, episode: int, incumbent: np.ndarray) -> tuple[float, str]:
        """J_eval of the incumbent if the schedule evaluates it, else NaN; at the last episode
        the final incumbent's evaluation episodes are stored. An incumbent whose evaluation
        fails (the plant runs away or diverges from a start, or raises) has J_eval = inf, with
        the error (the run goes on), as a training episode that fails is recorded."""
        if not self.schedule.step(episode, incumbent) or not self.evaluates:
            return math.nan, ""
        try:
            if episode == self.schedule.last:
                self.trajectories += self._final_episodes(episode, incumbent)
            return self.evaluator.J_eval(incumbent), ""
        except EPISODE_FAILURES as err:
            self.evaluator.remember(incumbent, math.inf)
            what = (
                str(err) if isinstance(err, FloatingPointError) else f"{type(err).__name__}: {err}"
            )
            return math.inf, f"evaluation: {what}"

    def episodes(self, max_episodes: int | None = None) -> Iterator[EpisodeRow]:
        """Step until the budget is done (or ``max_episodes`` more episodes), yielding each
        episode's row: the events that checkpointing and progress hang on."""
        remaining = self.settings.episodes - self.run.episode
        for _ in range(remaining if max_episodes is None else min(remaining, max_episodes)):
            yield self.step()

    def progress(self) -> dict:
        """The job's progress event (what the progress bars and lines show)."""
        return progress_event(
            self.learner, self.seed, self.rows, self.settings.episodes, not self.run.price.converged
        )

    def result(self) -> dict:
        """The job's result entry of ``summary.json``."""
        return {
            "learner": self.learner,
            "seed": self.seed,
            "episodes": self.run.episode,
            "done": self.done,
        }


def make_study_learner(
    settings: Settings, system: System, name: str, theta0: np.ndarray, seed: int
) -> Learner:
    """The learner ``name`` with the study's options for it, built by the registry for the
    study's start design (cycled or random starts); with identification (``system`` built for
    the job by :func:`~mpcmobo.experiment.build.build_system`, theta holding the identified
    parameters), given the model to identify (the registry then builds identify-first)."""
    options = settings.learner_options.get(name, {})
    starts = Starts(settings.start_mode, settings.n_cycle_starts)
    names = identified_parameters(settings, system, name)
    fit = ModelFit(system, names) if names else None
    return make_learner(
        name, system.search_space, theta0, seed=seed, starts=starts, model_fit=fit, **options
    )


def _learning_run(
    settings: Settings, system: System, learner: str, seed: int, plant: Any = None
) -> LearningRun:
    """The job's learning run: the learner tunes the imperfect-model MPC (eq. V0)."""
    mpc = ParametricMPC(system, model="imperfect", **settings.mpc.options())
    tuner = make_study_learner(settings, system, learner, mpc.theta0, seed)
    return LearningRun(
        system,
        tuner,
        mpc,
        seed=seed,
        steps=settings.steps,
        exploration_std=settings.exploration.std,
        exploration_decay=settings.exploration.decay,
        start_mode=settings.start_mode,
        n_cycle_starts=settings.n_cycle_starts,
        cycle_starts=settings.cycle_starts,
        critic_ridge=settings.critic.ridge,
        critic_method=settings.critic.method,
        critic_q_target=settings.critic.q_target,
        critic_min_valid_steps=settings.critic.min_valid_steps,
        critic_weighting=settings.critic.weighting,
        beta=settings.beta,
        plant=plant,
        price=ExplorationPrice(
            settings.exploration.budget,
            settings.episodes,
            identifies=bool(identified_parameters(settings, system, learner)),
        ),
    )


def explores(state: dict | None) -> bool:
    """Whether the job whose saved run state (:meth:`LearningRun.state_dict`) is ``state``
    still explores (its tuning has not stopped exploring, :mod:`mpcmobo.experiment.price`)."""
    return not ((state or {}).get("price") or {}).get("converged")


def progress_event(
    learner: str, seed: int, rows: list[EpisodeRow], total: int, exploring: bool = True
) -> dict:
    """The progress event of a job after ``rows``: its last f1, best evaluated J_eval and
    whether it still explores."""
    J = [r.J_eval_incumbent for r in rows if math.isfinite(r.J_eval_incumbent)]
    return {
        "kind": "episode",
        "learner": learner,
        "seed": seed,
        "episode": len(rows),
        "episodes": total,
        "f1": float(rows[-1].f1) if rows else math.nan,
        "best_J_eval": float(min(J)) if J else math.nan,
        "exploring": bool(exploring),
    }


@contextmanager
def single_threaded() -> Iterator[None]:
    """One BLAS / OpenMP / torch thread while a job runs (the parallelism is across jobs);
    the thread counts of the calling process are restored afterwards."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        with threadpool_limits(limits=1):
            yield
    finally:
        torch.set_num_threads(threads)


def run_job(
    settings_dict: dict,
    out_dir: str,
    learner_name: str,
    seed: int,
    J_initial: float | None = None,
    max_episodes: int | None = None,
    on_episode: Progress | None = None,
    parent_pid: int | None = None,
    system_factory: Callable[..., System] | None = None,
) -> dict:
    """Run (or continue) the job (learner, seed) until its budget; checkpoint every episode.

    ``parent_pid``: in a worker process, the pid of the study's process. If that process dies
    (killed, not interrupted), the job stops after its current episode's checkpoint instead of
    running on as an orphan that a later ``--resume`` would race with (the worker's watchdog,
    :func:`mpcmobo.experiment.interrupts.init_worker`, stops it sooner: at the end of the current
    MPC step). An interrupt raises :class:`~mpcmobo.experiment.interrupts.Interrupted` with
    every finished episode checkpointed. Library warnings go to ``DIR/run.log``.
    ``system_factory``: in a worker process, the factory of the settings' system, registered
    here under its name (a worker does not see what the study's process registered).
    """
    if system_factory is not None:
        register_system(settings_dict["system"]["name"], system_factory, overwrite=True)
    interrupts.check()  # told to stop before this job started
    settings = validate_settings(settings_dict)
    guard = interrupts.worker_job() if parent_pid is not None else interrupts.active()
    source = f"{learner_name}-s{seed}"
    with guard, run_log(out_dir, source, capture_output=parent_pid is not None), single_threaded():
        job = Job(settings, RunDirectory(out_dir), learner_name, seed, J_initial)
        job.restore()
        for _ in job.episodes(max_episodes):
            job.save()
            if on_episode is not None:
                on_episode(job.progress())
            if parent_pid is not None and os.getppid() != parent_pid:
                break  # orphaned: the study is gone; everything so far is checkpointed
    return job.result()
