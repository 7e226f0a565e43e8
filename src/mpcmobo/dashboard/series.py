"""The page's numbers of one job and of a learner's seeds, from the episode rows.

Per job (:func:`job_series`): each episode's plant cost (the ``plant_cost`` column, else the
episode's mean stage cost) and its running sum, the excess over the deployed controller where
recorded, J_eval of the deployed theta where it was evaluated, every change of the deployed
theta with the episodes behind it, the identified parameters, and f1..f4 with their Pareto
front. Per learner (:func:`group_series`): the median and the spread (min, max) over seeds, by
episode.
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import pandas as pd

from mpcmobo.bo.pareto import pareto_mask
from mpcmobo.dashboard.jsonable import floats, floats2, number

__all__ = ["changes", "group_series", "job_series", "plant_cost"]

OBJECTIVES = ("f1", "f2", "f3", "f4")


def _column(df: pd.DataFrame, name: str) -> np.ndarray:
    """A numeric column as floats (NaN where it is missing)."""
    if name not in df.columns:
        return np.full(len(df), np.nan)
    return pd.to_numeric(df[name], errors="coerce").to_numpy(float)


def _matrix(values: Any, width: int | None = None) -> np.ndarray:
    """A column of lists as an (n, width) array, NaN rows where a list has another length."""
    rows = [np.asarray(v, float).ravel() if v is not None else np.zeros(0) for v in values]
    if width is None:
        width = max((len(r) for r in rows), default=0)
    out = np.full((len(rows), width), np.nan)
    for i, r in enumerate(rows):
        if len(r) == width:
            out[i] = r
    return out


def plant_cost(df: pd.DataFrame) -> np.ndarray:
    """Each episode's cost on the plant: ``plant_cost`` where recorded, else the episode's
    mean stage cost."""
    recorded = _column(df, "plant_cost")
    return np.where(np.isfinite(recorded), recorded, _column(df, "mean_stage_cost"))


def changes(
    df: pd.DataFrame, theta0: np.ndarray | None, names: list[str], cost: np.ndarray
) -> list[dict[str, Any]]:
    """Every change of the deployed theta: the episode after which it changed, the
    parameters that changed, and the evidence in the job's episodes so far (how many ran the
    new and the old theta, and their mean plant cost)."""
    inc = _matrix(df["incumbent"]) if "incumbent" in df.columns else np.zeros((len(df), 0))
    theta = _matrix(df["theta"], inc.shape[1]) if "theta" in df.columns else inc * np.nan
    episodes = df["episode"].to_numpy(int)
    prev = theta0 if theta0 is not None and len(theta0) == inc.shape[1] else None
    # the rows whose incumbent differs from the row before's (the first: from theta0)
    before = np.vstack([inc[:1] * np.nan if prev is None else prev[None, :], inc[:-1]])
    moved = ~np.all(np.abs(inc - before) <= 1e-12, axis=1) & np.all(np.isfinite(inc), axis=1)
    out = []
    for i in np.flatnonzero(moved):
        new = inc[i]
        if prev is not None and np.allclose(new, prev, rtol=0, atol=1e-12):
            continue  # back to the deployed theta after a row without an incumbent
        diff = [] if prev is None else np.flatnonzero(np.abs(new - prev) > 1e-12).tolist()
        ran_new = np.all(np.isclose(theta[: i + 1], new, rtol=0, atol=1e-9), axis=1)
        ran_old = (
            np.all(np.isclose(theta[: i + 1], prev, rtol=0, atol=1e-9), axis=1)
            if prev is not None
            else np.zeros(i + 1, bool)
        )
        out.append(
            {
                "episode": int(episodes[i]),
                "changed": [
                    [names[j] if j < len(names) else f"theta{j}", number(prev[j]), number(new[j])]
                    for j in diff
                    if prev is not None
                ],
                "new_runs": int(ran_new.sum()),
                "new_cost": number(np.nanmean(cost[: i + 1][ran_new])) if ran_new.any() else None,
                "old_runs": int(ran_old.sum()),
                "old_cost": number(np.nanmean(cost[: i + 1][ran_old])) if ran_old.any() else None,
                "J_eval": number(df["J_eval_incumbent"].iloc[i])
                if "J_eval_incumbent" in df.columns
                else None,
                "first": prev is None,
            }
        )
        prev = new
    return out


def _objectives(df: pd.DataFrame) -> dict[str, Any] | None:
    """f1..f4 of the episodes and the indices of their Pareto front (minimisation, over the
    episodes with all four finite); None where no episode has them."""
    Y = np.column_stack([_column(df, f) for f in OBJECTIVES])
    ok = np.all(np.isfinite(Y), axis=1)
    if not ok.any():
        return None
    front = np.flatnonzero(ok)[pareto_mask(Y[ok])]
    return {"values": floats2(Y.T), "front": front.tolist()}


def job_series(
    df: pd.DataFrame, theta0: np.ndarray | None, theta_names: list[str]
) -> dict[str, Any]:
    """The numbers of one job (its rows, in episode order) for the page."""
    cost = plant_cost(df)
    excess = _column(df, "excess_cost")
    J = _column(df, "J_eval_incumbent")
    ident = _matrix(df["identified"]) if "identified" in df.columns else np.zeros((len(df), 0))
    errors = df["error"].astype(str).to_numpy() if "error" in df.columns else np.array([])
    refused = df["refused"].astype(str).to_numpy() if "refused" in df.columns else np.array([])
    return {
        "episode": df["episode"].astype(int).tolist(),
        "cost": floats(cost),
        "cum_cost": floats(np.nancumsum(cost)),
        "cost_recorded": bool(np.isfinite(_column(df, "plant_cost")).any()),
        "excess": floats(excess) if np.isfinite(excess).any() else None,
        "cum_excess": floats(np.nancumsum(excess)) if np.isfinite(excess).any() else None,
        "J_eval": floats(np.where(np.isposinf(J), np.nan, J)),
        "ran_away": [int(e) for e, j in zip(df["episode"], J) if np.isposinf(j)],
        "violation": floats(_column(df, "violation")),
        "changes": changes(df, theta0, theta_names, cost),
        "identified": floats2(ident.T) if ident.shape[1] else [],
        "objectives": _objectives(df),
        "errors": [[int(e), m] for e, m in zip(df["episode"], errors) if m not in ("", "nan")],
        "refused": [[int(e), m] for e, m in zip(df["episode"], refused) if m not in ("", "nan")],
    }


def _deployed_level(J: np.ndarray) -> np.ndarray:
    """J_eval of the deployed theta carried forward over the episodes it was not evaluated."""
    return pd.Series(J).ffill().to_numpy(float)


def group_series(jobs: list[dict[str, Any]]) -> dict[str, Any]:
    """Median, min and max over the seeds of one learner, by episode index: the plant cost,
    its running sum and J_eval of the deployed theta (carried forward)."""
    n = max((len(j["episode"]) for j in jobs), default=0)

    def stack(key: str, transform: Any = None) -> np.ndarray:
        out = np.full((len(jobs), n), np.nan)
        for i, job in enumerate(jobs):
            v = np.array([np.nan if x is None else x for x in job[key]], float)
            out[i, : len(v)] = transform(v) if transform else v
        return out

    stats: dict[str, Any] = {"episode": list(range(n)), "seeds": len(jobs)}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # an episode no seed reached
        for key, m in (
            ("cost", stack("cost")),
            ("cum_cost", stack("cum_cost")),
            ("J_eval", stack("J_eval", _deployed_level)),
        ):
            stats[key] = {
                "median": floats(np.nanmedian(m, axis=0)),
                "min": floats(np.nanmin(m, axis=0)),
                "max": floats(np.nanmax(m, axis=0)),
            }
    return stats
