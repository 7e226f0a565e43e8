"""The records of a study: episodes.parquet, trajectories.parquet and summary.json.

:func:`write_records` rebuilds them from the jobs' checkpoints (after every study, interrupted
or not); :func:`summarize` condenses the episode rows into the per-seed and per-learner summary
(final and worst J_eval, episodes to the target, regressions, identified parameters at a bound).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from mpcmobo.experiment import storage
from mpcmobo.experiment.build import build_system, identified_parameters
from mpcmobo.experiment.logs import count_warnings
from mpcmobo.experiment.records import Reference
from mpcmobo.experiment.rundir import RunDirectory
from mpcmobo.experiment.settings import Settings
from mpcmobo.experiment.training_reference import training_summary
from mpcmobo.identify.fit import at_bounds, identification_bounds
from mpcmobo.systems.base import System

if TYPE_CHECKING:
    import pandas as pd


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
        # what tuning cost the plant: the sum of the episodes' mean stage costs, and of their
        # excess over the deployed controller from the same starts (the regret)
        "plant_cost": _sum_or_null(s, "plant_cost"),
        "excess_cost": _sum_or_null(s, "excess_cost"),
        "theta_final": [float(x) for x in s["incumbent"].iloc[-1]],
        "failed_episodes": _failed_episodes(s),
        "unsolved_episodes": _unsolved_episodes(s),
        "identified_final": _last_identified(s),
        "wall_time_s": float(wall_time_s),
    }


def _failed_episodes(s: pd.DataFrame) -> list[dict[str, Any]]:
    """The job's episodes that failed (no closed loop to learn from: the plant diverged or
    returned a state that is not finite, the episode broke), each ``{"episode", "error"}``
    (none in a file without the columns)."""
    if "mean_stage_cost" not in s.columns or "error" not in s.columns:
        return []
    failed = s[~np.isfinite(s["mean_stage_cost"].to_numpy(float))]
    return [
        {"episode": int(e), "error": str(err)}
        for e, err in zip(failed["episode"], failed["error"], strict=True)
    ]


def _unsolved_episodes(s: pd.DataFrame) -> list[dict[str, Any]]:
    """The job's recorded episodes in which MPC solves failed, each ``{"episode",
    "failed_solves"}``: at those steps the MPC's fallback input (the previous plan) drove the
    plant. A failed episode is in :func:`_failed_episodes` instead (none in a file without
    the columns)."""
    if "solver_failures" not in s.columns or "mean_stage_cost" not in s.columns:
        return []
    ran = np.isfinite(s["mean_stage_cost"].to_numpy(float))
    hit = s[ran & (s["solver_failures"].to_numpy() > 0)]
    return [
        {"episode": int(e), "failed_solves": int(n)}
        for e, n in zip(hit["episode"], hit["solver_failures"], strict=True)
    ]


def _sum_or_null(s: pd.DataFrame, column: str) -> float | None:
    """The sum of a column's finite values over the job's episodes (None: none, or an older
    file without the column)."""
    if column not in s.columns:
        return None
    v = s[column].to_numpy(float)
    return float(np.sum(v[np.isfinite(v)])) if np.isfinite(v).any() else None


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
        "failed_episodes": int(sum(len(v.get("failed_episodes", [])) for v in vals)),
        "unsolved_episodes": int(sum(len(v.get("unsolved_episodes", [])) for v in vals)),
        "seeds_with_regressions": sum(1 for v in vals if v["regressions"] > 0),
        **_best_seed_theta(per_seed),
        "theta_names": theta_names,
        "identified_names": list(identified),
        **_bounds_summary(system, identified, per_seed),
        "wall_time_s": float(sum(v["wall_time_s"] for v in vals)) if vals else 0.0,
        "complete": bool(vals)
        and all(v["complete"] for v in vals)
        and len(vals) == len(settings.seeds),
        "per_seed": per_seed,
    }


def _best_seed_theta(per_seed: dict[str, Any]) -> dict[str, Any]:
    """The deployed theta of the seed whose final J_eval is the lowest (``theta_final``, the
    seed: ``theta_final_seed``); where no seed was evaluated, the first seed's."""
    if not per_seed:
        return {"theta_final": None, "theta_final_seed": None}
    evaluated = {k: v for k, v in per_seed.items() if v["J_final"] is not None}
    pool = evaluated or per_seed
    seed = min(pool, key=lambda k: pool[k]["J_final"]) if evaluated else next(iter(pool))
    return {"theta_final": per_seed[seed]["theta_final"], "theta_final_seed": int(seed)}


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
    summary["stopped_exploring"] = stopped_exploring(ckpts)
    storage.write_json(out / "summary.json", summary)
    return summary


def stopped_exploring(ckpts: list[dict]) -> dict[str, list[dict]]:
    """Per learner, the jobs whose tuning stopped exploring (:mod:`mpcmobo.experiment.price`)
    with when and why: ``{"seed", "episode", "reason"}`` each (``episode``: that of the last
    refused candidate; None in a run saved before it was kept)."""
    stops: dict[str, list[dict]] = {}
    for c in ckpts:
        price = (c.get("state") or {}).get("price") or {}
        if price.get("converged"):
            stops.setdefault(c["learner"], []).append(
                {
                    "seed": int(c["seed"]),
                    "episode": price.get("converged_at"),
                    "reason": str(price["converged"]),
                }
            )
    return stops
