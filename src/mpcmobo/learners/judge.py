"""The deployment judge: the tests every learner's deployments rest on, read from its
:class:`~mpcmobo.learners.evidence.Evidence`.

A deployment policy (:mod:`mpcmobo.learners.deploy` for the GP learners and identification,
MPC-RL's verification blocks in :mod:`mpcmobo.learners.mpc_rl`) chooses the rows of the
candidate and of the deployed theta; the judge turns them into the confidence that the
candidate is cheaper (:mod:`mpcmobo.learners.confidence`):

* :func:`paired_differences`: cycled starts, like for like: per episode of the candidate
  (``per="episode"``, the GP learners) or per start (``per="start"``, a verification block's
  means), the deployed theta's mean cost from the same start minus the candidate's;
* :func:`twin_verdict`: once a twin judges (identify-first), the prediction-powered test of the
  same plant episodes, each with the twin's prediction, and the twin's costs on its simulated
  starts (:func:`~mpcmobo.learners.confidence.twin_confidence`).

Under random starts without a twin the policies call
:func:`~mpcmobo.learners.confidence.adjusted_confidence` on the rows' costs and start costs.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from mpcmobo.learners.confidence import twin_confidence
from mpcmobo.learners.evidence import Evidence
from mpcmobo.learners.prediction import Twin

__all__ = ["paired_differences", "twin_sides", "twin_verdict"]


def paired_differences(
    y: np.ndarray,
    starts: np.ndarray,
    cand: np.ndarray,
    dep: np.ndarray,
    per: Literal["episode", "start"] = "episode",
) -> np.ndarray:
    """The deployed theta's mean cost ``y`` from a start minus the candidate's, for each of the
    candidate's rows ``cand`` (``per="episode"``) or each of its starts in increasing order
    (``per="start"``, the candidate's mean there), where the deployed theta's rows ``dep`` have
    that start; empty without a common start."""
    d = []
    if per == "episode":
        for i in cand:
            same = dep[starts[dep] == starts[i]]
            if len(same):
                d.append(float(np.mean(y[same])) - float(y[i]))
        return np.asarray(d, float)
    for s in np.unique(starts[cand]):
        own = dep[starts[dep] == s]
        if len(own):
            d.append(float(np.mean(y[own])) - float(np.mean(y[cand[starts[cand] == s]])))
    return np.asarray(d, float)


def twin_sides(
    ev: Evidence,
    twin: Twin,
    rows: tuple[np.ndarray, np.ndarray],
    points: tuple[np.ndarray, np.ndarray],
    paired: bool,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """The plant's costs (``ev.costs``) and the twin's predictions of them, for the deployed
    theta and the candidate (``rows`` and ``points`` in that order): per start both ran from
    (``paired``), else per episode."""
    out = []
    common = sorted(set(ev.starts[rows[0]].tolist()) & set(ev.starts[rows[1]].tolist()))
    for r, z in zip(rows, points):
        if paired:
            out.append(twin.per_start(z, r, ev.starts, ev.costs, ev.replays, common))
        else:
            out.append((ev.costs[r], twin.predict(z, [ev.replays[int(i)] for i in r])))
    return out


def twin_verdict(
    ev: Evidence,
    twin: Twin,
    rows: tuple[np.ndarray, np.ndarray],
    points: tuple[np.ndarray, np.ndarray],
    paired: bool,
) -> float:
    """The prediction-powered confidence that the candidate (``points[1]``, its episodes
    ``rows[1]``) is cheaper than the deployed theta (``points[0]``, ``rows[0]``)."""
    (y_d, p_d), (y_c, p_c) = twin_sides(ev, twin, rows, points, paired)
    return twin_confidence(
        (y_d, p_d, twin.simulate(points[0])), (y_c, p_c, twin.simulate(points[1])), paired
    )
