"""How confident the evidence is that a candidate theta is cheaper than the deployed one.

Every deployment decision of the learners rests on the episode costs the two thetas had on the
plant, never on J_eval and never on the model alone. Each function returns the confidence of a
one-sided test (a number in [0, 1]; a policy deploys at ``confidence`` 0.9 by default and
considers a candidate worth running again from 0.5):

* :func:`paired_confidence`: per-start differences (cycled starts: like for like);
* :func:`unpaired_confidence`: Welch's test (random starts, no covariate);
* :func:`adjusted_confidence`: the analysis of covariance on each episode's start cost, with a
  leverage guard (random starts);
* :func:`relative_screen`: the screen of a candidate with a single episode a side, where the
  tests have no degrees of freedom;
* :func:`twin_confidence`: the prediction-powered test, where the identified model (the twin)
  predicts every episode and the mean over many simulated starts, and the plant's episodes
  correct the twin's error.

Costs are compared in their own units (J is a mean of episode costs, and a few costly starts
can carry it), so a theta cheaper from most starts in log cost can still be judged dearer.
"""

from __future__ import annotations

import numpy as np
from scipy.stats import t as student_t
from scipy.stats import ttest_ind

__all__ = [
    "adjusted_confidence",
    "ancova_confidence",
    "check_confidence",
    "paired_confidence",
    "relative_screen",
    "twin_confidence",
    "unpaired_confidence",
]


def check_confidence(name: str, value: float) -> float:
    """``value`` as a float if it is a confidence in [0.5, 1), else a ``ValueError`` naming
    the option ``name``."""
    if not 0.5 <= float(value) < 1:
        raise ValueError(f"{name} must be in [0.5, 1), got {value}")
    return float(value)


def paired_confidence(d: np.ndarray) -> float:
    """The one-sided t-test of ``mean(d) > 0``, ``F_t(n-1)(mean / (sd / sqrt(n)))``: ``d`` (n,)
    the per-start advantages of the candidate (the deployed theta's cost minus the
    candidate's). One difference: 0.5 if positive (enough to be run again, never to be
    deployed), else 0; no spread: 1 or 0 by the sign of the mean."""
    d = np.asarray(d, float)
    d = d[np.isfinite(d)]
    if len(d) == 0:
        return 0.0
    if len(d) == 1:
        return 0.5 if d[0] > 0 else 0.0
    sd = float(np.std(d, ddof=1))
    mean = float(np.mean(d))
    if sd == 0:
        return 1.0 if mean > 0 else 0.0
    return float(student_t.cdf(mean / (sd / np.sqrt(len(d))), df=len(d) - 1))


def unpaired_confidence(deployed: np.ndarray, candidate: np.ndarray) -> float:
    """The one-sided Welch t-test of ``mean(deployed) > mean(candidate)`` on the two thetas'
    episode costs (the spread of the starts is part of the standard error). Fewer than two
    episodes on a side: 0.5 if the candidate's mean is lower, else 0."""
    d = np.asarray(deployed, float)
    c = np.asarray(candidate, float)
    d, c = d[np.isfinite(d)], c[np.isfinite(c)]
    if len(c) == 0 or len(d) == 0:
        return 0.0
    diff = float(np.mean(d) - np.mean(c))
    if len(c) < 2 or len(d) < 2:
        return 0.5 if diff > 0 else 0.0
    if np.var(d) + np.var(c) == 0:  # no spread on either side: the statistic is undefined
        return 1.0 if diff > 0 else 0.0
    return 1.0 - float(ttest_ind(d, c, equal_var=False, alternative="greater").pvalue)


def _finite_episodes(
    deployed: np.ndarray, candidate: np.ndarray, s_deployed: np.ndarray, s_candidate: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The episodes of each side with a finite cost, each with its covariate."""
    y_d, y_c = np.asarray(deployed, float), np.asarray(candidate, float)
    s_d, s_c = np.asarray(s_deployed, float), np.asarray(s_candidate, float)
    keep_d, keep_c = np.isfinite(y_d), np.isfinite(y_c)
    return y_d[keep_d], y_c[keep_c], s_d[keep_d], s_c[keep_c]


def adjusted_confidence(
    deployed: np.ndarray,
    candidate: np.ndarray,
    s_deployed: np.ndarray,
    s_candidate: np.ndarray,
) -> float:
    r"""The unpaired test adjusted for how costly each episode's start was: the analysis of
    covariance of the costs ``y`` on the start covariate ``s`` with a common slope,

    .. math:: y_i = a + \delta\,[i \text{ is the candidate's}] + b\,s_i + e_i,

    and the one-sided t-test of ``delta < 0`` (:func:`ancova_confidence`). Under random starts
    the covariate does not depend on which theta runs, so ``delta`` estimates the difference
    of the expected costs, and the spread the starts explain leaves the test.

    No decision rests on one episode: the result is the smaller of the test on all episodes and
    the test without the episode of the highest leverage (the largest diagonal element of the
    hat matrix, ``1/n_g + (s_i - sbar_g)^2 / S_ss``): on the CSTR a single hot-spot start
    (cost 30 times the others) can set the slope and credit a candidate that never met such a
    start. Falls back to :func:`unpaired_confidence` where the covariate is missing, a side
    has fewer than two episodes, or the covariate has no spread within the groups."""
    y_d, y_c, s_d, s_c = _finite_episodes(deployed, candidate, s_deployed, s_candidate)
    full = ancova_confidence(y_d, y_c, s_d, s_c)
    if full is None:
        return unpaired_confidence(y_d, y_c)
    S_ss = float(np.sum((s_d - s_d.mean()) ** 2) + np.sum((s_c - s_c.mean()) ** 2))
    lev = np.concatenate(
        [
            1 / len(s_d) + (s_d - s_d.mean()) ** 2 / S_ss,
            1 / len(s_c) + (s_c - s_c.mean()) ** 2 / S_ss,
        ]
    )
    i = int(np.argmax(lev))
    if i < len(y_d):
        y_d, s_d = np.delete(y_d, i), np.delete(s_d, i)
    else:
        y_c, s_c = np.delete(y_c, i - len(y_d)), np.delete(s_c, i - len(y_d))
    without = ancova_confidence(y_d, y_c, s_d, s_c)
    return min(full, unpaired_confidence(y_d, y_c) if without is None else without)


def ancova_confidence(
    y_d: np.ndarray, y_c: np.ndarray, s_d: np.ndarray, s_c: np.ndarray
) -> float | None:
    r"""The one-sided ANCOVA t-test on the given episodes (finite costs): by least squares
    ``delta = (ybar_c - ybar_d) - b (sbar_c - sbar_d)``, ``b`` the pooled within-group slope,
    ``se^2 = MSE (1 / n_c + 1 / n_d + (sbar_c - sbar_d)^2 / S_ss)``, ``F_t(n-3)(-delta / se)``.
    None where it is undefined: a covariate not finite, a side with fewer than two episodes,
    or no spread of the covariate within the groups."""
    if len(y_d) < 2 or len(y_c) < 2 or not (np.all(np.isfinite(s_d)) and np.all(np.isfinite(s_c))):
        return None
    S_ss = float(np.sum((s_d - s_d.mean()) ** 2) + np.sum((s_c - s_c.mean()) ** 2))
    if S_ss <= 0:
        return None
    S_sy = float(
        np.sum((s_d - s_d.mean()) * (y_d - y_d.mean()))
        + np.sum((s_c - s_c.mean()) * (y_c - y_c.mean()))
    )
    b = S_sy / S_ss  # the pooled within-group slope
    delta = (y_c.mean() - y_d.mean()) - b * (s_c.mean() - s_d.mean())
    r = np.concatenate(
        [y_d - y_d.mean() - b * (s_d - s_d.mean()), y_c - y_c.mean() - b * (s_c - s_c.mean())]
    )
    dof = len(r) - 3
    se2 = float(r @ r) / dof * (1 / len(y_c) + 1 / len(y_d) + (s_c.mean() - s_d.mean()) ** 2 / S_ss)
    if se2 <= 0:  # an exact fit: the sign decides
        return 1.0 if delta < 0 else 0.0
    return float(student_t.cdf(-delta / np.sqrt(se2), df=dof))


def relative_screen(
    deployed: np.ndarray,
    candidate: np.ndarray,
    s_deployed: np.ndarray,
    s_candidate: np.ndarray,
) -> float:
    r"""The screen of a candidate while a side has a single episode (random starts): 0.5 when
    its cost relative to its starts, the ratio of means :math:`\sum_i y_i / \sum_i s_i`, is
    below the deployed theta's, else 0 -- enough to be run again, never to be deployed.

    At one episode a side the tests have no degrees of freedom and compare raw costs, which
    judges the luck of the start. The ratio of means is the cost model of a start that costs in
    proportion to its covariate (what the covariate is built to be) and, unlike the mean of the
    ratios, is not carried by a start near the equilibrium. Without a positive covariate on
    every episode, the raw means."""
    y_d, y_c, s_d, s_c = _finite_episodes(deployed, candidate, s_deployed, s_candidate)
    if len(y_d) == 0 or len(y_c) == 0:
        return 0.0
    s_ok = np.all(np.isfinite(s_d)) and np.all(np.isfinite(s_c))
    if s_ok and np.all(s_d > 0) and np.all(s_c > 0):
        cand, dep = y_c.sum() / s_c.sum(), y_d.sum() / s_d.sum()
    else:
        cand, dep = y_c.mean(), y_d.mean()
    return 0.5 if cand < dep else 0.0


def twin_confidence(
    deployed: tuple[np.ndarray, np.ndarray, np.ndarray],
    candidate: tuple[np.ndarray, np.ndarray, np.ndarray],
    paired: bool,
) -> float:
    r"""The twin's test that the candidate is cheaper on the distribution of starts: the
    plant's episodes calibrate the twin's predictions, and the twin's simulated starts carry
    the calibrated prediction to the distribution (prediction-powered inference, Angelopoulos
    et al., *Science* 382, 2023, in the form of the ratio estimator, Cochran, *Sampling
    Techniques*, ch. 6).

    Each side is ``(y, yhat, sim)``: the plant's costs of its episodes, the twin's predictions
    of the same episodes (closed loops on the identified model from the same initial states,
    each with its episode's exploration replayed) and the twin's costs on ``M`` simulated
    starts drawn from the distribution, the same starts for both sides. ``paired``: ``y[i]``
    of both sides come from the same start ``i`` (cycled starts). Per side, the twin's mean on
    the simulated starts is scaled by how far the plant's episodes exceed its predictions of
    them,

    .. math:: \hat J = \overline{sim}\;\frac{\sum_i y_i}{\sum_i \hat y_i},
        \qquad \hat\Delta = \hat J_{deployed} - \hat J_{candidate},

    so a twin that is right (ratio 1) lends the test its ``M`` starts, and one that is wrong by
    a factor is corrected by it. Costs are heavy-tailed (a few hot starts carry the mean), and
    a model's error grows with how costly the start is: a ratio, unlike the difference of
    PPI's rectifier, carries what a few cool plant starts say to the hot ones. The variance
    is the jackknife's over the plant's episodes (starts, when paired; within each side
    otherwise) plus the simulated starts' ``var / M``; the confidence is
    ``F_t(nu)(hat Delta / se)`` with Welch-Satterthwaite's ``nu``. Without two usable
    episodes a side (a finite cost and prediction, a positive sum of predictions) or two
    finite simulated starts, the test is the plain one (:func:`paired_confidence`,
    :func:`unpaired_confidence`)."""
    (y_d, yh_d, m_d), (y_c, yh_c, m_c) = (
        tuple(np.asarray(a, float) for a in side) for side in (deployed, candidate)
    )
    ok_sim = np.isfinite(m_d) & np.isfinite(m_c)
    if paired:
        keep = np.isfinite(y_d) & np.isfinite(yh_d) & np.isfinite(y_c) & np.isfinite(yh_c)
        sides = [(y_d[keep], yh_d[keep]), (y_c[keep], yh_c[keep])]
    else:
        sides = [_finite_pairs(y, yh) for y, yh in ((y_d, yh_d), (y_c, yh_c))]
    usable = all(len(y) >= 2 and np.all(yh > 0) for y, yh in sides)
    if np.count_nonzero(ok_sim) < 2 or not usable:
        return paired_confidence(y_d - y_c) if paired else unpaired_confidence(y_d, y_c)
    est, parts = _ratio_estimate(sides, m_d[ok_sim], m_c[ok_sim], paired)
    var = sum(v for v, _ in parts)
    if var <= 0:  # no spread anywhere: the sign decides
        return 1.0 if est > 0 else 0.0
    dof = var**2 / sum(v**2 / df for v, df in parts if v > 0)
    return float(student_t.cdf(est / np.sqrt(var), df=dof))


Side = tuple[np.ndarray, np.ndarray]


def _finite_pairs(y: np.ndarray, yh: np.ndarray) -> Side:
    """The episodes whose cost ``y`` and prediction ``yh`` are both finite."""
    keep = np.isfinite(y) & np.isfinite(yh)
    return y[keep], yh[keep]


def _ratio_estimate(
    sides: list[Side], m_d: np.ndarray, m_c: np.ndarray, paired: bool
) -> tuple[float, list[tuple[float, int]]]:
    """:func:`twin_confidence`'s estimate of the deployed theta's cost minus the candidate's
    and its variance in parts, each with its degrees of freedom: the simulated starts', then
    the jackknife's over the plant's starts (paired) or over each side's episodes."""
    means = (float(np.mean(m_d)), float(np.mean(m_c)))

    def estimate(d: Side, c: Side) -> float:
        return means[0] * d[0].sum() / d[1].sum() - means[1] * c[0].sum() / c[1].sum()

    def drop(side: Side, i: int) -> Side:
        return np.delete(side[0], i), np.delete(side[1], i)

    d, c = sides
    r_d, r_c = d[0].sum() / d[1].sum(), c[0].sum() / c[1].sum()
    M = len(m_d)
    parts = [(float(np.var(r_d * m_d - r_c * m_c, ddof=1)) / M, M - 1)]
    if paired:
        loo = [estimate(drop(d, i), drop(c, i)) for i in range(len(d[0]))]
        parts.append((_jackknife(np.array(loo)), len(loo) - 1))
    else:
        for k, side in enumerate(sides):
            loo = [_ratio(means[k], drop(side, i)) for i in range(len(side[0]))]
            parts.append((_jackknife(np.array(loo)), len(loo) - 1))
    return estimate(d, c), parts


def _ratio(mean: float, side: Side) -> float:
    """``mean`` times the ratio of the side's plant costs to the twin's predictions."""
    return mean * side[0].sum() / side[1].sum()


def _jackknife(leave_one_out: np.ndarray) -> float:
    """The jackknife variance of an estimate from its leave-one-out values."""
    n = len(leave_one_out)
    return float((n - 1) / n * np.sum((leave_one_out - leave_one_out.mean()) ** 2))
