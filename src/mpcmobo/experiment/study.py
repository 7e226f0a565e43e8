"""A study: learners x seeds learning runs, evaluated and recorded, resumable after a crash.

``run_study(settings, out_dir)`` opens the run directory (:func:`open_run`: ``config.toml``
holds every setting), computes the study-level :class:`Reference` (J*, J_eval(theta0) and their
evaluation episodes) once, then runs one :class:`Job` per (learner, seed), in parallel worker
processes. After every episode a job rewrites its checkpoint atomically; ``resume=True``
continues each job from its checkpoint with the saved settings, and since an episode depends
only on that state, the records equal those of an uninterrupted run (wall-time columns aside).
Resumed with a larger ``episodes``, a run is extended to that budget, and its records equal those
of a run started with it. When a job evaluates its incumbent and what it stores is the
:class:`EvaluationSchedule` (in :mod:`mpcmobo.experiment.job`).
"""

from __future__ import annotations

import math
import os
import pickle
import signal
import time
from collections.abc import Callable, Collection
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mpcmobo.experiment import interrupts, storage
from mpcmobo.experiment.evaluation import make_evaluator, mean_cost, no_J_star_reason
from mpcmobo.experiment.job import Progress, make_study_learner, progress_event, run_job
from mpcmobo.experiment.logs import count_warnings, run_log
from mpcmobo.experiment.loop import EPISODE_FAILURES
from mpcmobo.experiment.records import Reference, Trajectory
from mpcmobo.experiment.rundir import RunDirectory, StudyError, open_run
from mpcmobo.experiment.settings import (
    Settings,
    SettingsError,
    build_plant,
    build_system,
    identified_parameters,
)
from mpcmobo.experiment.training_reference import training_references, training_summary
from mpcmobo.identify.fit import at_bounds, identification_bounds
from mpcmobo.learners.registry import LEARNER_SPECS
from mpcmobo.mpc.codegen import require_compiler
from mpcmobo.systems.base import System, SystemDefinitionError
from mpcmobo.systems.plant import check_reset
from mpcmobo.systems.registry import is_registered, system_factory

if TYPE_CHECKING:
    from concurrent.futures import Future, ProcessPoolExecutor

    import pandas as pd

# relative cost per episode of a learner's job, to start the slowest jobs first
JOB_COST = {name: spec.job_cost for name, spec in LEARNER_SPECS.items()}


# ---------------------------------------------------------------------- building blocks
def system_info(system: System) -> dict:
    """What the figures need to know about the system (JSON-safe: inf -> None)."""
    return {
        "name": system.name,
        "description": system.description,
        "state_names": list(system.state_names),
        "input_names": list(system.input_names),
        "dt": float(system.dt),
        "x_ref": system.x_ref.tolist(),
        "u_ref": system.u_ref.tolist(),
        "x_lb": system.x_lb.tolist(),
        "x_ub": system.x_ub.tolist(),
        "u_lb": system.u_lb.tolist(),
        "u_ub": system.u_ub.tolist(),
        "theta_names": list(system.parameterization.names),
        "param_names": list(system.param_names),
        "nominal_params": np.asarray(system.models["imperfect"], float).tolist(),
        "true_params": None
        if system.true_params is None
        else np.asarray(system.true_params, float).tolist(),
    }


def check_learners(settings: Settings) -> None:
    """The system can be built, its plant made and matched to it, and every learner accepts
    its options (else a SettingsError naming them), before anything is written."""
    system = build_system(settings)
    plant = build_plant(settings, system)
    try:
        check_reset(plant, system, settings.system.measurement_noise)
    except SystemDefinitionError as err:
        raise SettingsError(f"system.plant: {err}") from None
    finally:
        plant.close()
    try:
        if settings.mpc.codegen:
            require_compiler()
    except RuntimeError as err:
        raise SettingsError(f"mpc.codegen: {err}") from None
    for name in settings.learners:
        job_system = build_system(settings, name)
        try:
            theta0 = job_system.parameterization.theta0
            make_study_learner(settings, job_system, name, theta0, seed=0)
        except (TypeError, ValueError) as err:
            raise SettingsError(f"learner_options.{name}: {err}") from None


def compute_reference(settings: Settings) -> Reference:
    """J*, J_eval(theta0) and the evaluation episodes of theta0 ("initial") and perfect MPC."""
    system = build_system(settings)
    evaluator = make_evaluator(settings, system)
    phases: list[tuple[str, str, np.ndarray | None]] = [
        ("initial", "imperfect", evaluator.mpc("imperfect").theta0.copy())
    ]
    if evaluator.has_J_star:
        phases.append(("perfect", "perfect", None))
    for _, model, _ in phases:  # an interrupt ends a solve, never fails it
        interrupts.guard_solves(evaluator.mpc(model))
    theta0 = evaluator.mpc("imperfect").theta0.copy()
    t0 = time.perf_counter()
    trajectories = []
    values = {}
    for phase, model, theta in phases:
        try:
            eps = evaluator.episodes(theta, model)
        except EPISODE_FAILURES as err:
            what = "J(theta0), theta0's MPC" if phase == "initial" else "J*, the perfect MPC"
            raise StudyError(
                f"computing {what} on the plant from the evaluation starts failed: "
                f"{type(err).__name__}: {err}. Every J_eval is measured against these; check the "
                "plant (docs/user-systems.md) and run again"
            ) from None
        values[phase] = mean_cost(eps)
        trajectories += [
            Trajectory(phase, -1, i, r.x.copy(), r.u.copy()) for i, r in enumerate(eps)
        ]
    # J~*, like for like: needs the perfect model
    training = training_references(settings, system) if evaluator.has_J_star else []
    return Reference(
        J_star=values.get("perfect"),
        J_initial=values["initial"],
        theta0=theta0,
        system=system_info(system),
        trajectories=trajectories,
        wall_time_s=time.perf_counter() - t0,
        J_star_missing=None if evaluator.has_J_star else no_J_star_reason(system),
        training=training,
    )


# ---------------------------------------------------------------------- summary
def _first_within(df: pd.DataFrame, reference: Reference, tol: float) -> int | None:
    """The first episode whose J_eval is within ``tol`` of J* or, without J*, that improves
    on J_initial (theta0) by at least ``tol``."""
    ok = df[np.isfinite(df["J_eval_incumbent"])]
    if reference.J_star is not None:
        J_star = float(reference.J_star)
        ok = ok[ok["J_eval_incumbent"] - J_star <= tol * abs(J_star)]
    else:
        J0 = float(reference.J_initial)
        ok = ok[ok["J_eval_incumbent"] - J0 <= -tol * abs(J0)]
    return int(ok["episode"].min()) if len(ok) else None


def _target(reference: Reference) -> str:
    """What ``episodes_to_2pct`` / ``episodes_to_5pct`` count to (``episodes_to_target``)."""
    if reference.J_star is not None:
        return "J_eval within 2% / 5% of J_star"
    return "J_eval at least 2% / 5% below J_initial (no J_star)"


def _median_or_null(values: list[float | None]) -> float | None:
    """Median with null counted as +inf (not reached); null if the median is not reached."""
    if not values:
        return None
    v = np.array([math.inf if x is None else float(x) for x in values])
    m = float(np.median(v))
    if not math.isfinite(m):
        return None
    return int(m) if m.is_integer() else m


def _seed_summary(
    s: pd.DataFrame, settings: Settings, reference: Reference, wall_time_s: float
) -> dict[str, Any]:
    """The summary of one job from its rows ``s`` (sorted by episode)."""
    evaluated = s[~np.isnan(s["J_eval_incumbent"])]  # inf: the plant ran away
    J = evaluated["J_eval_incumbent"].to_numpy(float)
    violation = s["violation"].to_numpy(float)
    return {
        "J_final": float(J[-1]) if len(J) else None,
        # the worst J_eval of the deployed theta over the run, and how many
        # evaluations found it worse than theta0 (J_eval > J_initial)
        "J_worst": float(J.max()) if len(J) else None,
        "regressions": int(np.count_nonzero(J > float(reference.J_initial))),
        "violation_mean": float(np.nanmean(violation)) if np.isfinite(violation).any() else None,
        "episodes_done": len(s),
        "complete": int(s["episode"].max()) == settings.episodes - 1,
        "episodes_to_2pct": _first_within(s, reference, 0.02),
        "episodes_to_5pct": _first_within(s, reference, 0.05),
        "theta_final": [float(x) for x in s["incumbent"].iloc[-1]],
        "identified_final": _last_identified(s),
        "wall_time_s": float(wall_time_s),
    }


def _last_identified(s: pd.DataFrame) -> list[float] | None:
    """The model parameters identified after the job's last episode (None: none)."""
    if "identified" not in s.columns:
        return None
    last = s["identified"].iloc[-1]
    return None if last is None or len(last) == 0 else [float(x) for x in last]


def _learner_summary(
    name: str, per_seed: dict[str, Any], settings: Settings, reference: Reference
) -> dict[str, Any]:
    """The summary of one learner: medians over its seeds' summaries ``per_seed``."""
    vals = list(per_seed.values())
    system = build_system(settings, name)
    theta_names = list(system.parameterization.names)
    identified = identified_parameters(settings, system, name)
    J_finals = [v["J_final"] for v in vals if v["J_final"] is not None]
    J_final = float(np.median(J_finals)) if J_finals else None
    worst = [v["J_worst"] for v in vals if v["J_worst"] is not None]
    return {
        "J_star": None if reference.J_star is None else float(reference.J_star),
        "J_initial": float(reference.J_initial),
        "J_final": J_final,
        "improvement_over_theta0": None
        if J_final is None
        else 1.0 - J_final / float(reference.J_initial),
        "episodes_to_2pct": _median_or_null([v["episodes_to_2pct"] for v in vals]),
        "episodes_to_5pct": _median_or_null([v["episodes_to_5pct"] for v in vals]),
        # the worst seed: its final J_eval, and the worst deployed J_eval of any seed
        "J_final_worst": max(J_finals) if J_finals else None,
        "J_worst": max(worst) if worst else None,
        "regressions": int(sum(v["regressions"] for v in vals)),
        "seeds_with_regressions": sum(1 for v in vals if v["regressions"] > 0),
        "theta_final": vals[0]["theta_final"] if vals else None,
        "theta_names": theta_names,
        "identified_names": list(identified),
        **_bounds_summary(system, identified, per_seed),
        "wall_time_s": float(sum(v["wall_time_s"] for v in vals)) if vals else 0.0,
        "complete": bool(vals)
        and all(v["complete"] for v in vals)
        and len(vals) == len(settings.seeds),
        "per_seed": per_seed,
    }


def _bounds_summary(
    system: System, names: tuple[str, ...], per_seed: dict[str, Any]
) -> dict[str, Any]:
    """The identified parameters' bounds (``identified_bounds``: name -> [lower, upper]) and
    those the final fit of some seed sits on (``identified_at_bound``: name, "lower" or
    "upper", the bound and the seeds)."""
    if not names:
        return {"identified_bounds": {}, "identified_at_bound": []}
    lo, hi = identification_bounds(system, names)
    seeds: dict[tuple[int, str], list[int]] = {}
    for seed, v in per_seed.items():
        q = v.get("identified_final")
        if q is None or len(q) != len(names):
            continue
        for side, on in zip(("lower", "upper"), at_bounds(np.asarray(q, float), lo, hi)):
            for j in np.flatnonzero(on):
                seeds.setdefault((int(j), side), []).append(int(seed))
    return {
        "identified_bounds": {n: [float(lo[j]), float(hi[j])] for j, n in enumerate(names)},
        "identified_at_bound": [
            {
                "name": names[j],
                "bound": side,
                "value": float((lo if side == "lower" else hi)[j]),
                "seeds": sorted(s),
            }
            for (j, side), s in sorted(seeds.items())
        ],
    }


def summarize(settings: Settings, reference: Reference, df: pd.DataFrame, wall_times: dict) -> dict:
    """The per-learner summary of the records ``df`` (episodes.parquet)."""
    learners: dict[str, Any] = {}
    for name in settings.learners:
        sub = df[df["learner"] == name] if len(df) else df
        per_seed: dict[str, Any] = {}
        for seed in settings.seeds:
            s = sub[sub["seed"] == seed].sort_values("episode") if len(sub) else sub
            if len(s):
                wall = wall_times.get((name, seed), math.nan)
                per_seed[str(seed)] = _seed_summary(s, settings, reference, wall)
        learners[name] = _learner_summary(name, per_seed, settings, reference)
    return {
        "system": reference.system.get("name", settings.system.name),
        "J_star": None if reference.J_star is None else float(reference.J_star),
        "J_star_missing": reference.J_star_missing,
        "episodes_to_target": _target(reference),
        "J_initial": float(reference.J_initial),
        "theta0": np.asarray(reference.theta0).tolist(),
        "theta_names": reference.system["theta_names"],
        "system_info": reference.system,
        "complete": all(v["complete"] for v in learners.values()),
        "learners": learners,
        "settings": settings.to_dict(),
    }


def write_records(
    out_dir: str | Path, settings: Settings, reference: Reference | None
) -> dict | None:
    """(Re)build episodes.parquet, trajectories.parquet and summary.json from the checkpoints
    (a damaged latest checkpoint: the previous generation, see :meth:`RunDirectory.checkpoint`);
    the summary counts the warnings logged in ``run.log`` (``warnings``)."""
    out = Path(out_dir)
    run_dir = RunDirectory(out)
    ckpts = []
    for n in settings.learners:
        for s in settings.seeds:
            ckpt = run_dir.checkpoint(n, s)
            if ckpt is not None:
                ckpts.append(dict(ckpt.to_dict(), learner=ckpt.learner, seed=ckpt.seed))
    df = storage.episodes_frame(ckpts)
    storage.write_parquet(out / "episodes.parquet", df)
    if reference is None:
        return None
    info = reference.system
    traj = storage.trajectories_frame(
        reference.to_dict(), ckpts, info["state_names"], info["input_names"], info["dt"]
    )
    storage.write_parquet(out / "trajectories.parquet", traj)
    wall = {(c["learner"], c["seed"]): c["wall_time_s"] for c in ckpts}
    summary = summarize(settings, reference, df, wall)
    summary["reference_wall_time_s"] = reference.wall_time_s
    summary.update(training_summary(reference))
    summary["warnings"] = count_warnings(out)
    storage.write_json(out / "summary.json", summary)
    return summary


# ---------------------------------------------------------------------- the study
def run_study(
    settings: Settings | None,
    out_dir: str | Path,
    resume: bool = False,
    progress: Progress | None = None,
    max_episodes_this_call: int | None = None,
) -> dict:
    """Run the study (or continue it with ``resume=True``); return the summary dict.

    ``max_episodes_this_call`` stops every job after that many episodes of this call (used to
    simulate an interruption); the summary then has ``complete: false``.

    SIGINT and SIGTERM stop the study (in the main thread): the jobs stop at the end of their
    current MPC step, the workers are stopped, the records are rebuilt from the checkpoints
    and :class:`~mpcmobo.experiment.interrupts.Interrupted` (a ``KeyboardInterrupt``) is
    raised. Library warnings go to ``DIR/run.log`` (:mod:`mpcmobo.experiment.logs`).
    """
    with interrupts.catching():
        if settings is not None and not resume:
            check_learners(settings)  # a bad learner option fails before anything is written
        if resume and RunDirectory(out_dir).is_tuner():
            raise StudyError(
                f"{out_dir} holds a tuner (ask and tell): its trials run on the plant, not in "
                f"mpcmobo run. Go on with `mpcmobo ask {out_dir}`; `mpcmobo ask {out_dir} "
                "--episodes N` extends its budget"
            )
        run_dir, settings = open_run(out_dir, settings, resume)
        with run_log(run_dir.path, "study"):
            return _run_study(run_dir, settings, resume, progress, max_episodes_this_call)


def _run_study(
    run_dir: RunDirectory,
    settings: Settings,
    resume: bool,
    progress: Progress | None,
    max_episodes_this_call: int | None,
) -> dict:
    if resume:
        check_learners(settings)
    emit = progress or (lambda event: None)
    jobs = [(n, s) for n in settings.learners for s in settings.seeds]
    emit({"kind": "start", "jobs": jobs, "episodes": settings.episodes,
          "out_dir": str(run_dir.path)})  # fmt: skip
    reference = _reference(run_dir, settings, emit)
    args = dict(
        settings_dict=settings.to_dict(),
        out_dir=str(run_dir.path),
        J_initial=reference.J_initial,
        max_episodes=max_episodes_this_call,
    )
    try:
        _run_jobs(_pending(run_dir, settings, jobs, emit), args, settings, run_dir, emit)
    finally:
        with interrupts.deferred():  # the records of what is checkpointed, written whole
            summary = write_records(run_dir.path, settings, reference)
    emit({"kind": "done", "summary": summary})
    return summary  # type: ignore[return-value]  # a dict: the reference exists


def _reference(run_dir: RunDirectory, settings: Settings, emit: Progress) -> Reference:
    """The study's reference: computed once, then read from the run directory."""
    reference = run_dir.reference()
    if reference is None:
        emit({"kind": "reference", "status": "running"})
        reference = compute_reference(settings)
        run_dir.save_reference(reference)
    emit({"kind": "reference", "status": "done", "J_star": reference.J_star,
          "J_initial": reference.J_initial})  # fmt: skip
    return reference


def _pending(
    run_dir: RunDirectory, settings: Settings, jobs: list[tuple[str, int]], emit: Progress
) -> list[tuple[str, int]]:
    """The jobs with episodes left (unfinished or extended), longest first: with fewer workers
    than jobs, the slowest job does not start last. Reports the progress of the others."""
    pending = []
    for n, s in jobs:
        ckpt = run_dir.checkpoint(n, s)
        if ckpt is not None:
            emit(progress_event(n, s, ckpt.rows, settings.episodes))
        if ckpt is None or len(ckpt.rows) < settings.episodes:
            pending.append((n, s))
    pending.sort(key=lambda job: -JOB_COST.get(job[0], LEARNER_SPECS[job[0]].job_cost))
    return pending


def _run_jobs(
    jobs: list[tuple[str, int]],
    args: dict,
    settings: Settings,
    run_dir: RunDirectory,
    emit: Progress,
) -> None:
    """Run the jobs here, one after the other, or in worker processes (``settings.backend``)."""
    if settings.workers == 1 or len(jobs) <= 1 and settings.backend == "process":
        for n, s in jobs:
            run_job(learner_name=n, seed=s, on_episode=emit, **args)
        return
    if settings.system.factory is None and is_registered(settings.system.name):
        # registered in this process: the workers get the factory (pickled by reference);
        # factory paths and plug-ins are imported by the workers from the settings
        args = dict(args, system_factory=system_factory(settings.system.name))
    watch = _Watch(run_dir, jobs, settings.episodes, emit)
    if settings.backend == "ray":
        _run_ray(jobs, args, settings.workers, watch)
    else:
        _run_processes(jobs, args, settings.workers, watch)


class _Watch:
    """Reports the progress of jobs in other processes by reading their checkpoints."""

    def __init__(
        self, run_dir: RunDirectory, jobs: list[tuple[str, int]], total: int, emit: Progress
    ) -> None:
        self.run_dir, self.jobs, self.total, self.emit = run_dir, jobs, total, emit
        self.seen: dict[tuple[str, int], int] = {}

    def poll(self) -> None:
        """Report the jobs whose checkpoint changed since the last poll."""
        for n, s in self.jobs:
            try:
                mtime = storage.checkpoint_path(self.run_dir.path, n, s).stat().st_mtime_ns
            except FileNotFoundError:
                continue
            if self.seen.get((n, s)) == mtime:
                continue
            self.seen[(n, s)] = mtime
            try:
                ckpt = self.run_dir.checkpoint(n, s)
            except Exception:  # noqa: BLE001 - being replaced right now; next poll
                continue
            if ckpt is not None:
                self.emit(progress_event(n, s, ckpt.rows, self.total))


def _sendable(factory: Callable[..., System]) -> None:
    """A system factory must reach the worker processes by reference (pickle)."""
    try:
        pickle.dumps(factory)
    except (pickle.PicklingError, AttributeError, TypeError) as err:
        raise StudyError(
            f"the system factory {factory!r} cannot be sent to worker processes ({err}); "
            "register a function defined at module level, or run with workers = 1"
        ) from None


def _run_processes(
    jobs: list[tuple[str, int]], args: dict[str, Any], workers: int, watch: _Watch
) -> None:
    """The jobs in a pool of spawned worker processes. Each worker ignores SIGINT and watches
    the study's process (:func:`interrupts.init_worker`); if the study stops (interrupt, or a
    job's error), the file ``DIR/.stop`` tells the busy workers to stop at the end of their current MPC
    step, and those that do not within :data:`STOP_TIMEOUT_S` are terminated."""
    import multiprocessing as mp
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    if args.get("system_factory") is not None:
        _sendable(args["system_factory"])
    ctx = mp.get_context("spawn")  # no CasADi / torch state is inherited through fork
    stop = watch.run_dir.path / STOP_FILE
    stop.unlink(missing_ok=True)  # left by a study that was killed while stopping
    pool = ProcessPoolExecutor(
        max_workers=min(workers, len(jobs)),
        mp_context=ctx,
        initializer=interrupts.init_worker,
        initargs=(os.getpid(), str(stop)),
    )
    # the workers are spawned by the submits below; they start with SIGINT blocked (a signal
    # mask survives fork and exec), so a Ctrl-C while a worker still imports, before
    # init_worker ignores SIGINT, cannot raise inside its start-up; a SIGINT that reaches the
    # study meanwhile is delivered to it when the mask is restored
    old_mask = (
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        if hasattr(signal, "pthread_sigmask")  # not on Windows
        else None
    )
    try:
        futures = {
            pool.submit(run_job, learner_name=n, seed=s, parent_pid=os.getpid(), **args): (n, s)
            for n, s in jobs
        }
    finally:
        if old_mask is not None:
            signal.pthread_sigmask(signal.SIG_SETMASK, old_mask)
    remaining = set(futures)
    try:
        while remaining:
            done, remaining = wait(remaining, timeout=0.5, return_when=FIRST_COMPLETED)
            watch.poll()
            for f in done:
                f.result()  # re-raise a job's error here
    except BaseException:
        with interrupts.deferred():
            try:
                _stop_pool(pool, stop, remaining)
            finally:
                stop.unlink(missing_ok=True)
        raise
    pool.shutdown(wait=True)


STOP_TIMEOUT_S = 10.0  # how long stopped workers may take to finish their current MPC step
STOP_FILE = ".stop"  # in the run directory while the study stops its workers


def _stop_pool(pool: ProcessPoolExecutor, stop: Path, remaining: Collection[Future[Any]]) -> None:
    """Stop the workers: cancel what has not started, tell the busy ones to stop (their jobs
    end at the end of the current MPC step, with everything finished checkpointed), wait for
    their jobs to report, then end the worker processes. They are killed rather than waited
    for: a worker's interpreter takes seconds to tear down (torch, CasADi), and all it has to
    keep is already on disk (checkpoints and the log are written whole)."""
    from concurrent.futures import wait

    stop.touch()
    for f in remaining:
        f.cancel()
    processes = list((getattr(pool, "_processes", None) or {}).values())
    wait(remaining, timeout=STOP_TIMEOUT_S)
    for p in processes:
        p.kill()
    for p in processes:
        p.join(timeout=STOP_TIMEOUT_S)
    pool.shutdown(wait=False, cancel_futures=True)


def _run_ray(
    jobs: list[tuple[str, int]], args: dict[str, Any], workers: int, watch: _Watch
) -> None:
    try:
        import ray
    except ImportError:
        raise SettingsError(
            "backend: 'ray' needs the optional dependency ray (pip install 'mpcmobo[ray]'); "
            "allowed without it: 'process'"
        ) from None
    started = not ray.is_initialized()  # a cluster of the study's own, shut down after it
    if started:
        ray.init(num_cpus=workers, include_dashboard=False, ignore_reinit_error=True)
        interrupts.reclaim()  # Ray's SIGTERM handler would end the study without a word
    remote = ray.remote(num_cpus=1)(run_job)
    refs = [remote.remote(learner_name=n, seed=s, **args) for n, s in jobs]
    try:
        while refs:
            ready, refs = ray.wait(refs, timeout=0.5)
            watch.poll()
            for r in ready:
                ray.get(r)
    except BaseException:
        with interrupts.deferred():
            for r in refs:  # checkpoints are atomic: a killed task loses its episode only
                ray.cancel(r, force=True)
        raise
    finally:
        if started:  # its processes stop now, not after an interrupted CLI has exited
            with interrupts.deferred():
                ray.shutdown()
