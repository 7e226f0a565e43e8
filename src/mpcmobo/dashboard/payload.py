"""What the page shows of one run, as plain JSON data: the run's description (system, limits,
J*, theta0's level, parameters), its jobs' series and their seeds' medians, the stored
trajectories, a tuner's state and every message about a file that could not be read."""

from __future__ import annotations

from typing import Any

import numpy as np

from mpcmobo.dashboard.jsonable import floats, number, plain
from mpcmobo.dashboard.runs import RunSource
from mpcmobo.dashboard.series import group_series, job_series
from mpcmobo.experiment.records import Reference
from mpcmobo.experiment.settings import Settings

__all__ = ["run_payload"]


def _system(reference: Reference | None) -> dict[str, Any] | None:
    """The system's names and limits (from the reference, which describes it)."""
    if reference is None:
        return None
    return plain(reference.system)


def _deploy_options(raw: dict[str, Any], learner: str) -> str | None:
    """The learner's ``deploy`` option as written in ``config.toml`` (None: its default)."""
    options = raw.get("learner_options", {})
    deploy = options.get(learner, {}).get("deploy") if isinstance(options, dict) else None
    if deploy is None:
        return None
    if isinstance(deploy, dict):
        return ", ".join(f"{k} = {v}" for k, v in deploy.items())
    return str(deploy)


def _tuner(
    source: RunSource, status: dict[str, Any] | None, live: dict[tuple[str, int], dict]
) -> dict[str, Any] | None:
    """A tuner's pending trial, recommendation and trials (``status.json`` where written;
    the pending trial from its checkpoint otherwise)."""
    if not source.is_tuner() and status is None:
        return None
    out: dict[str, Any] = {"status": plain(status) if status else None, "pending": None}
    for ckpt in live.values():
        pending = ckpt.get("pending")
        if isinstance(pending, dict):
            out["pending"] = {
                "episode": pending.get("episode"),
                "theta": floats(pending["theta"]) if "theta" in pending else None,
            }
    if status is not None and out["pending"] is None and status.get("pending") is not None:
        out["pending"] = {"episode": status.get("pending"), "theta": None}
    return out


def _state(
    running: bool,
    ckpt: dict | None,
    rows: Any,
    settings: Settings | None,
    summary: Any,
) -> str:
    """What the page says of a job: ``running``; ``recorded`` where it ran its budget (its
    checkpoint done, or its last episode the budget's last); else ``stopped`` (Ctrl-C, or a
    study killed before it wrote a summary, or during an extension of a complete one). Without
    the settings, the summary's ``complete`` decides."""
    if running:
        return "running"
    if ckpt is not None and ckpt.get("done", False):
        return "recorded"
    if settings is not None:
        finished = len(rows) > 0 and int(rows["episode"].max()) >= settings.episodes - 1
    else:
        finished = not isinstance(summary, dict) or bool(summary.get("complete", True))
    return "recorded" if finished else "stopped"


def _identified(
    source: RunSource, settings: Settings | None, reference: Reference | None, jobs: list[dict]
) -> dict[str, Any] | None:
    """The identified parameters' names with their nominal and true values."""
    n = max((len(j["identified"]) for j in jobs), default=0)
    if n == 0:
        return None
    names = source.identified_names(settings, n)
    info = reference.system if reference is not None else {}
    all_names = list(info.get("param_names", []))

    def value(key: str, name: str) -> float | None:
        values = info.get(key)
        if values is None or name not in all_names:
            return None
        return number(values[all_names.index(name)])

    return {
        "names": names,
        "nominal": [value("nominal_params", p) for p in names],
        "true": [value("true_params", p) for p in names],
    }


def _start(
    source: RunSource, settings: Settings | None, reference: Reference | None, rows: Any
) -> tuple[np.ndarray | None, list[str]]:
    """The job's first deployed theta and the names of its entries: theta0, and where the
    job identifies the model, the nominal values of the parameters it appends to theta."""
    if reference is None or "incumbent" not in rows.columns or rows.empty:
        return None, []
    theta0 = np.asarray(reference.theta0, float).ravel()
    names = list(reference.system.get("theta_names", []))
    width = len(np.asarray(rows["incumbent"].iloc[0], float).ravel())
    if width == len(theta0):
        return theta0, names
    extra = source.identified_names(settings, width - len(theta0))
    nominal = dict(
        zip(reference.system.get("param_names", []), reference.system.get("nominal_params", []))
    )
    if width < len(theta0) or any(p not in nominal for p in extra):
        return None, names + extra
    return np.concatenate([theta0, [float(nominal[p]) for p in extra]]), names + extra


def _trajectory_keys(index: Any, live: dict[tuple[str, int], dict]) -> list[list[Any]]:
    """(learner, seed, phase, episode, start) of every stored trajectory: the records', and
    those of the checkpoints newer than the records (a study in progress)."""
    keys = plain(index.to_numpy().tolist())
    known = {tuple(k) for k in keys}
    for (learner, seed), ckpt in live.items():
        for t in ckpt.get("trajectories", []):
            key = [learner, seed, str(t["phase"]), int(t["episode"]), int(t["start"])]
            if tuple(key) not in known:
                keys.append(key)
    return keys


# how many of a job's episode errors the page names (the rest are counted)
ERRORS_SHOWN = 3


def _episode_errors(jobs: list[dict[str, Any]]) -> list[str]:
    """A line per episode whose record holds an error (a failed episode, a failed proposal or
    evaluation), the first ``ERRORS_SHOWN`` of each job, then how many more."""
    lines = []
    for job in jobs:
        errors = job.get("errors") or []
        who = f"{job['learner']} seed {job['seed']}"
        lines += [f"{who}, episode {e}: {m}" for e, m in errors[:ERRORS_SHOWN]]
        if len(errors) > ERRORS_SHOWN:
            lines.append(f"{who}: {len(errors) - ERRORS_SHOWN} more episodes with an error")
    return lines


def run_payload(source: RunSource, index: int) -> dict[str, Any]:
    """Everything the page shows of the run of ``source`` (the ``index``-th of the page)."""
    source.begin()
    settings = source.settings()
    raw = source.raw_config()
    reference = source.reference()
    summary = source.summary()
    status = source.status()
    episodes, live = source.episodes()
    _, index_frame = source.trajectories()
    theta0 = None if reference is None else np.asarray(reference.theta0, float).ravel()
    learners = list(settings.learners) if settings is not None else []
    learners += [lr for lr in episodes["learner"].unique().tolist() if lr not in learners]
    jobs = []
    alive = source.study_alive()
    for (learner, seed), rows in episodes.groupby(["learner", "seed"], sort=False):
        start, names = _start(source, settings, reference, rows)
        job = job_series(rows.sort_values("episode"), start, names)
        ckpt = live.get((learner, seed))
        running = ckpt is not None and not ckpt.get("done", False) and alive
        state = _state(running, ckpt, rows, settings, summary)
        head = {"learner": str(learner), "seed": int(seed), "live": running, "state": state}
        jobs.append({**head, "deploy": _deploy_options(raw, str(learner)), **job})
    jobs.sort(key=lambda j: (learners.index(j["learner"]), j["seed"]))
    groups = {
        lr: group_series([j for j in jobs if j["learner"] == lr])
        for lr in learners
        if any(j["learner"] == lr for j in jobs)
    }
    return {
        "index": index,
        "path": str(source.path),
        "name": source.path.name or str(source.path),
        "kind": "tuner" if source.is_tuner() else "run",
        "budget": settings.episodes if settings is not None else None,
        "seeds": list(settings.seeds) if settings is not None else [],
        "learners": learners,
        "system": _system(reference),
        "J_star": number(reference.J_star) if reference is not None else None,
        "J_star_missing": reference.J_star_missing if reference is not None else None,
        "J_initial": number(reference.J_initial) if reference is not None else None,
        "theta0": floats(theta0) if theta0 is not None else None,
        "jobs": jobs,
        "groups": groups,
        "identified": _identified(source, settings, reference, jobs),
        "trajectories": _trajectory_keys(index_frame, live),
        "tuner": _tuner(source, status, live),
        "complete": bool(summary.get("complete", True)) if isinstance(summary, dict) else None,
        "messages": list(dict.fromkeys([*source.messages, *_episode_errors(jobs)])),
    }
