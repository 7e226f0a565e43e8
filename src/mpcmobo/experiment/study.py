"""A study: learners x seeds learning runs, evaluated and recorded, resumable after a crash.

``run_study(settings, out_dir)`` writes ``config.toml``, computes the study-level reference
(J*, J_eval(theta0) and their evaluation episodes) once, then runs one job per (learner, seed),
in parallel worker processes. A job builds its own system, MPC, learner and evaluator (no CasADi
object crosses a process boundary) and, after every episode, rewrites its checkpoint atomically:
the :class:`LearningRun` state (learner and random generators), every row so far, the stored
trajectories and the evaluation-policy state. ``run_study(..., resume=True)`` continues each job
from its checkpoint with the saved ``config.toml``; since an episode depends only on that state,
the records equal those of an uninterrupted run (wall-time columns aside). Resumed with settings
whose ``episodes`` is larger, a run is extended to that budget, and its records equal those of a
run started with it (:func:`_reopen` undoes what only the old last episode recorded).

Evaluation policy: the incumbent's J_eval is computed at episode 0, at the last episode, and
whenever the incumbent differs from the last evaluated one and at least ``eval_every`` episodes
have passed since the last evaluation; ``J_eval_incumbent`` is NaN in the other rows.
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from mpcmobo.experiment import storage
from mpcmobo.experiment.settings import (
    Settings,
    SettingsError,
    build_system,
    load_settings,
    settings_to_toml,
    validate_settings,
)

Progress = Callable[[dict], None]


class StudyError(RuntimeError):
    """A study cannot run as asked (e.g. the output directory already holds another run)."""


# ---------------------------------------------------------------------- building blocks
def _mpc_options(settings: Settings) -> dict:
    return settings.mpc.options()


def make_evaluator(settings: Settings, system):
    from mpcmobo.experiment.evaluation import Evaluator

    ev = settings.evaluation
    return Evaluator(
        system,
        n_starts=ev.n_starts,
        seed=ev.seed,
        steps=ev.steps if ev.steps is not None else settings.steps,
        mpc_options=_mpc_options(settings),
    )


def system_info(system) -> dict:
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
    }


def check_learners(settings: Settings) -> None:
    """Every learner is installed and accepts its options (else a SettingsError)."""
    from mpcmobo.learners import LEARNERS, make_learner

    for name in settings.learners:
        if name not in LEARNERS:
            raise SettingsError(
                f"learners: '{name}' is not available in this installation; "
                f"registered learners: {', '.join(sorted(LEARNERS))}"
            )
    system = build_system(settings)
    space, theta0 = system.search_space, system.parameterization.theta0
    for name in settings.learners:
        try:
            make_learner(name, space, theta0, seed=0, **settings.learner_options.get(name, {}))
        except (TypeError, ValueError) as err:
            raise SettingsError(f"learner_options.{name}: {err}") from None


def compute_reference(settings: Settings) -> dict:
    """J*, J_eval(theta0) and the evaluation episodes of theta0 ("initial") and perfect MPC."""
    system = build_system(settings)
    evaluator = make_evaluator(settings, system)
    theta0 = evaluator.mpc("imperfect").theta0.copy()
    t0 = time.perf_counter()
    trajectories = []
    values = {}
    for phase, model, theta in (("initial", "imperfect", theta0), ("perfect", "perfect", None)):
        eps = evaluator.episodes(theta, model)
        values[phase] = float(np.mean([r.L.mean() for r in eps]))
        trajectories += [
            {"phase": phase, "episode": -1, "start": i, "x": r.x.copy(), "u": r.u.copy()}
            for i, r in enumerate(eps)
        ]
    return {
        "J_star": values["perfect"],
        "J_initial": values["initial"],
        "theta0": theta0,
        "system": system_info(system),
        "trajectories": trajectories,
        "wall_time_s": time.perf_counter() - t0,
    }


# ---------------------------------------------------------------------- one job
def _should_evaluate(episode: int, last: int, incumbent: np.ndarray, state: dict, every: int):
    if episode == 0 or episode == last:
        return True
    prev = state.get("theta")
    changed = prev is None or not np.array_equal(np.asarray(prev), incumbent)
    return changed and episode - state.get("episode", -(10**9)) >= every


# relative cost per episode of a learner's job, for scheduling only (measured in
# docs/benchmarks.md: the EHVI learners spend the most per episode, MPC-RL the least)
JOB_COST = {"mobo": 4, "hybrid": 4, "bo": 3, "mpc-rl": 1}


def run_job(
    settings_dict: dict,
    out_dir: str,
    learner_name: str,
    seed: int,
    J_initial: float | None = None,
    max_episodes: int | None = None,
    on_episode: Progress | None = None,
    parent_pid: int | None = None,
) -> dict:
    """Run (or continue) the job (learner, seed) until its budget; checkpoint every episode.

    ``parent_pid``: in a worker process, the pid of the study's process. If that process dies
    (killed, not interrupted), the job stops after its current episode's checkpoint instead of
    running on as an orphan that a later ``--resume`` would race with.
    """
    _limit_threads()
    from mpcmobo.experiment.loop import LearningRun
    from mpcmobo.learners import make_learner
    from mpcmobo.mpc import ParametricMPC

    settings = validate_settings(settings_dict)
    system = build_system(settings)
    mpc = ParametricMPC(system, model="imperfect", **_mpc_options(settings))
    learner = make_learner(
        learner_name,
        system.search_space,
        mpc.theta0,
        seed=seed,
        **settings.learner_options.get(learner_name, {}),
    )
    run = LearningRun(
        system,
        learner,
        mpc,
        seed=seed,
        steps=settings.steps,
        exploration_std=settings.exploration.std,
        exploration_decay=settings.exploration.decay,
        start_mode=settings.start_mode,
        n_cycle_starts=settings.n_cycle_starts,
        critic_ridge=settings.critic.ridge,
        critic_method=settings.critic.method,
        beta=settings.beta,
    )
    evaluator = make_evaluator(settings, system)
    if J_initial is not None:
        evaluator.remember(mpc.theta0, J_initial)
    ckpt = storage.load_checkpoint(out_dir, learner_name, seed)
    rows: list[dict] = []
    trajectories: list[dict] = []
    eval_state: dict = {}
    wall = 0.0
    if ckpt is not None:
        run.load_state_dict(ckpt["state"])
        rows, trajectories = list(ckpt["rows"]), list(ckpt["trajectories"])
        eval_state, wall = dict(ckpt["eval_state"]), float(ckpt["wall_time_s"])
        if len(rows) != run.episode:
            raise StudyError(f"checkpoint of {learner_name}-s{seed} is inconsistent")
    total, last = settings.episodes, settings.episodes - 1
    if ckpt is not None and int(ckpt["episodes"]) < total:  # the budget was extended
        eval_state = _reopen(rows, trajectories, settings)
    every_traj = settings.records.trajectory_every
    done_now = 0
    while run.episode < total and (max_episodes is None or done_now < max_episodes):
        t_start = time.perf_counter()
        row, record = run.run_episode()
        e = row["episode"]
        incumbent = np.asarray(row["incumbent"], dtype=float)
        t_eval = time.perf_counter()
        J = math.nan
        if _should_evaluate(e, last, incumbent, eval_state, settings.evaluation.eval_every):
            if e == last:  # the final incumbent: keep its evaluation episodes
                eps = evaluator.episodes(incumbent)
                if not evaluator.is_cached(incumbent):
                    evaluator.remember(incumbent, float(np.mean([r.L.mean() for r in eps])))
                trajectories += [
                    {"phase": "final", "episode": e, "start": i, "x": r.x.copy(), "u": r.u.copy()}
                    for i, r in enumerate(eps)
                ]
            J = evaluator.J_eval(incumbent)
            eval_state = {"theta": incumbent.copy(), "episode": e}
        row["J_eval_incumbent"] = J
        row["eval_time_s"] = time.perf_counter() - t_eval
        if record is not None and (e % every_traj == 0 or e == last):
            trajectories.append(
                {"phase": "learning", "episode": e, "start": 0, "x": record.x, "u": record.u}
            )
        rows.append(row)
        wall += time.perf_counter() - t_start
        storage.save_checkpoint(
            out_dir,
            learner_name,
            seed,
            {
                "state": run.state_dict(),
                "rows": rows,
                "trajectories": trajectories,
                "eval_state": eval_state,
                "wall_time_s": wall,
                "episodes": total,
                "done": run.episode >= total,
            },
        )
        done_now += 1
        if on_episode is not None:
            on_episode(_progress_event(learner_name, seed, rows, total))
        if parent_pid is not None and os.getppid() != parent_pid:
            break  # orphaned: the study is gone; everything so far is checkpointed
    return {
        "learner": learner_name,
        "seed": seed,
        "episodes": run.episode,
        "done": run.episode >= total,
    }


def _reopen(rows: list[dict], trajectories: list[dict], settings: Settings) -> dict:
    """Undo, in place, what only the end of the old budget recorded, so that a run extended
    to ``settings.episodes`` has the records of a run started with that budget: the final
    evaluation of the old last episode (kept only if the evaluation policy would have made it
    anyway), its "final" trajectories, and its off-grid "learning" trajectory. Returns the
    evaluation state as of the end of ``rows``."""
    state: dict = {}
    for row in rows[:-1]:
        if math.isfinite(row.get("J_eval_incumbent", math.nan)):
            state = {"theta": np.asarray(row["incumbent"], dtype=float), "episode": row["episode"]}
    if not rows:
        return state
    end = rows[-1]
    e, incumbent = end["episode"], np.asarray(end["incumbent"], dtype=float)
    if _should_evaluate(e, settings.episodes - 1, incumbent, state, settings.evaluation.eval_every):
        state = {"theta": incumbent.copy(), "episode": e}
    else:
        end["J_eval_incumbent"] = math.nan
    keep = [
        t
        for t in trajectories
        if not (t["episode"] == e and (t["phase"] == "final" or (
            t["phase"] == "learning" and e % settings.records.trajectory_every != 0)))
    ]  # fmt: skip
    trajectories[:] = keep
    return state


def _limit_threads() -> None:
    """One BLAS/torch thread per worker process: the parallelism is across jobs."""
    for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
        os.environ.setdefault(var, "1")
    if "torch" in sys.modules:
        try:
            sys.modules["torch"].set_num_threads(1)
        except Exception:  # noqa: BLE001 - best effort
            pass


def _progress_event(learner: str, seed: int, rows: list[dict], total: int) -> dict:
    J = [r["J_eval_incumbent"] for r in rows if np.isfinite(r.get("J_eval_incumbent", np.nan))]
    last = rows[-1] if rows else {}
    return {
        "kind": "episode",
        "learner": learner,
        "seed": seed,
        "episode": len(rows),
        "episodes": total,
        "f1": float(last.get("f1", math.nan)),
        "best_J_eval": float(min(J)) if J else math.nan,
    }


# ---------------------------------------------------------------------- summary
def _first_within(df, J_star: float, tol: float) -> int | None:
    ok = df[np.isfinite(df["J_eval_incumbent"])]
    ok = ok[ok["J_eval_incumbent"] - J_star <= tol * abs(J_star)]
    return int(ok["episode"].min()) if len(ok) else None


def _median_or_null(values: list[float | None]) -> float | None:
    """Median with null counted as +inf (not reached); null if the median is not reached."""
    if not values:
        return None
    v = np.array([math.inf if x is None else float(x) for x in values])
    m = float(np.median(v))
    if not math.isfinite(m):
        return None
    return int(m) if m.is_integer() else m


def summarize(settings: Settings, reference: dict, df, wall_times: dict) -> dict:
    """The per-learner summary of the records ``df`` (episodes.parquet)."""
    J_star, J_initial = float(reference["J_star"]), float(reference["J_initial"])
    names = reference["system"]["theta_names"]
    learners: dict[str, Any] = {}
    for name in settings.learners:
        sub = df[df["learner"] == name] if len(df) else df
        per_seed: dict[str, Any] = {}
        for seed in settings.seeds:
            s = sub[sub["seed"] == seed].sort_values("episode") if len(sub) else sub
            if not len(s):
                continue
            evaluated = s[np.isfinite(s["J_eval_incumbent"])]
            complete = int(s["episode"].max()) == settings.episodes - 1
            J_final = float(evaluated["J_eval_incumbent"].iloc[-1]) if len(evaluated) else None
            per_seed[str(seed)] = {
                "J_final": J_final,
                "episodes_done": len(s),
                "complete": complete,
                "episodes_to_2pct": _first_within(s, J_star, 0.02),
                "episodes_to_5pct": _first_within(s, J_star, 0.05),
                "theta_final": [float(x) for x in s["incumbent"].iloc[-1]],
                "wall_time_s": float(wall_times.get((name, seed), math.nan)),
            }
        vals = list(per_seed.values())
        J_finals = [v["J_final"] for v in vals if v["J_final"] is not None]
        first = vals[0] if vals else None
        learners[name] = {
            "J_star": J_star,
            "J_initial": J_initial,
            "J_final": float(np.median(J_finals)) if J_finals else None,
            "episodes_to_2pct": _median_or_null([v["episodes_to_2pct"] for v in vals]),
            "episodes_to_5pct": _median_or_null([v["episodes_to_5pct"] for v in vals]),
            "theta_final": first["theta_final"] if first else None,
            "theta_names": names,
            "wall_time_s": float(sum(v["wall_time_s"] for v in vals)) if vals else 0.0,
            "complete": bool(vals)
            and all(v["complete"] for v in vals)
            and len(vals) == len(settings.seeds),
            "per_seed": per_seed,
        }
    return {
        "system": settings.system.name,
        "J_star": J_star,
        "J_initial": J_initial,
        "theta0": np.asarray(reference["theta0"]).tolist(),
        "theta_names": names,
        "system_info": reference["system"],
        "complete": all(v["complete"] for v in learners.values()),
        "learners": learners,
        "settings": settings.to_dict(),
    }


def write_records(out_dir: str | Path, settings: Settings, reference: dict | None) -> dict | None:
    """(Re)build episodes.parquet, trajectories.parquet and summary.json from the checkpoints."""
    out = Path(out_dir)
    jobs = [(n, s) for n in settings.learners for s in settings.seeds]
    ckpts = storage.load_checkpoints(out, jobs)
    df = storage.episodes_frame(ckpts)
    storage.write_parquet(out / "episodes.parquet", df)
    if reference is None:
        return None
    info = reference["system"]
    traj = storage.trajectories_frame(
        reference, ckpts, info["state_names"], info["input_names"], info["dt"]
    )
    storage.write_parquet(out / "trajectories.parquet", traj)
    wall = {(c["learner"], c["seed"]): c["wall_time_s"] for c in ckpts}
    summary = summarize(settings, reference, df, wall)
    summary["reference_wall_time_s"] = reference.get("wall_time_s")
    storage.write_json(out / "summary.json", summary)
    return summary


# ---------------------------------------------------------------------- the study
def _prepare_dir(settings: Settings | None, out: Path, resume: bool) -> Settings:
    config = out / "config.toml"
    if resume:
        if not config.exists():
            raise StudyError(f"nothing to resume: {config} does not exist")
        saved = load_settings(config)
        if settings is not None:  # how the work is spread, and a larger budget, may change
            if settings.episodes < saved.episodes:
                raise StudyError(
                    f"episodes: the run in {out} has a budget of {saved.episodes}; a resumed "
                    f"run can be extended, not shortened (got {settings.episodes})"
                )
            extended = settings.episodes > saved.episodes
            saved = saved.model_copy(
                update={
                    "workers": settings.workers,
                    "backend": settings.backend,
                    "episodes": settings.episodes,
                }
            )
            if extended:  # the saved settings are those of the run from now on
                storage.atomic_write_text(config, settings_to_toml(saved))
        return saved
    if settings is None:
        raise StudyError("settings are required for a new study")
    if out.exists() and any(out.iterdir()):
        raise StudyError(
            f"{out} is not empty; choose a new --out directory or continue it with --resume"
        )
    resolved = settings.resolved()
    storage.atomic_write_text(config, settings_to_toml(resolved))
    return resolved


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
    """
    out = Path(out_dir)
    if settings is not None and not resume:
        check_learners(settings)  # a bad learner option fails before anything is written
    out.mkdir(parents=True, exist_ok=True)
    settings = _prepare_dir(settings, out, resume)
    if resume:
        check_learners(settings)
    emit = progress or (lambda event: None)
    jobs = [(n, s) for n in settings.learners for s in settings.seeds]
    emit({"kind": "start", "jobs": jobs, "episodes": settings.episodes, "out_dir": str(out)})
    ref_path = out / "reference.pkl"
    if ref_path.exists():
        reference = storage.read_pickle(ref_path)
    else:
        emit({"kind": "reference", "status": "running"})
        reference = compute_reference(settings)
        storage.write_pickle(ref_path, reference)
    emit({"kind": "reference", "status": "done", "J_star": reference["J_star"],
          "J_initial": reference["J_initial"]})  # fmt: skip
    pending = []
    for n, s in jobs:
        ckpt = storage.load_checkpoint(out, n, s)
        if ckpt is not None:
            emit(_progress_event(n, s, ckpt["rows"], settings.episodes))
        if ckpt is None or len(ckpt["rows"]) < settings.episodes:  # unfinished or extended
            pending.append((n, s))
    # longest jobs first (the GP learners' proposals cost more per episode than a gradient
    # step): with fewer workers than jobs, the slowest job does not start last
    pending.sort(key=lambda job: -JOB_COST.get(job[0], 2))
    args = dict(
        settings_dict=settings.to_dict(),
        out_dir=str(out),
        J_initial=reference["J_initial"],
        max_episodes=max_episodes_this_call,
    )
    try:
        if settings.workers == 1 or len(pending) <= 1 and settings.backend == "process":
            for n, s in pending:
                run_job(learner_name=n, seed=s, on_episode=emit, **args)
        elif settings.backend == "ray":
            _run_ray(pending, args, settings.workers, out, settings.episodes, emit)
        else:
            _run_processes(pending, args, settings.workers, out, settings.episodes, emit)
    finally:
        summary = write_records(out, settings, reference)
    emit({"kind": "done", "summary": summary})
    return summary


def _poll(out: Path, jobs: list[tuple[str, int]], total: int, emit: Progress, seen: dict) -> None:
    """Report progress by reading the job checkpoints that changed since the last poll."""
    for n, s in jobs:
        path = storage.checkpoint_path(out, n, s)
        try:
            mtime = path.stat().st_mtime_ns
        except FileNotFoundError:
            continue
        if seen.get((n, s)) == mtime:
            continue
        seen[(n, s)] = mtime
        try:
            ckpt = storage.read_pickle(path)
        except Exception:  # noqa: BLE001 - being replaced right now; next poll
            continue
        emit(_progress_event(n, s, ckpt["rows"], total))


def _run_processes(jobs, args, workers, out, total, emit) -> None:
    import multiprocessing as mp
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    ctx = mp.get_context("spawn")  # no CasADi / torch state is inherited through fork
    seen: dict = {}
    with ProcessPoolExecutor(max_workers=min(workers, len(jobs)), mp_context=ctx) as pool:
        futures = {
            pool.submit(run_job, learner_name=n, seed=s, parent_pid=os.getpid(), **args): (n, s)
            for n, s in jobs
        }
        remaining = set(futures)
        try:
            while remaining:
                done, remaining = wait(remaining, timeout=0.5, return_when=FIRST_COMPLETED)
                _poll(out, jobs, total, emit, seen)
                for f in done:
                    f.result()  # re-raise a job's error here
        except BaseException:
            for f in remaining:
                f.cancel()
            raise


def _run_ray(jobs, args, workers, out, total, emit) -> None:
    try:
        import ray
    except ImportError:
        raise SettingsError(
            "backend: 'ray' needs the optional dependency ray (pip install 'mpcmobo[ray]'); "
            "allowed without it: 'process'"
        ) from None
    if not ray.is_initialized():
        ray.init(num_cpus=workers, include_dashboard=False, ignore_reinit_error=True)
    remote = ray.remote(num_cpus=1)(run_job)
    refs = [remote.remote(learner_name=n, seed=s, **args) for n, s in jobs]
    seen: dict = {}
    while refs:
        ready, refs = ray.wait(refs, timeout=0.5)
        _poll(out, jobs, total, emit, seen)
        for r in ready:
            ray.get(r)
