"""Which theta is deployed, and which are safe (issue 11, items 2-3).

The deployed theta (the incumbent, what J_eval measures) changes only when the learner's own
surrogate says a candidate is better in expectation over the initial states with probability
at least ``deploy_confidence``: ``P(J(new) < J(current)) >= deploy_confidence``, estimated
from joint posterior samples of the two expectations (common contexts, one joint posterior).
Candidates are the thetas the learner has run. A theta is *safe* when the
``safety_confidence`` quantile of its expected violation is at most the violation budget;
only safe candidates are deployed.

The default budget (``violation_budget = "auto"``) is relative to theta0 (safe by
assumption): ``2 x`` theta0's expected violation per episode over the contexts (the posterior
mean, re-estimated at every fit from all episodes) plus an absolute floor from the system's
state bounds (:class:`~mpcmobo.bo.context.ContextSpec`, 0.1% of the summed widths), so it is
scale-free. A first version set it from theta0's first episode alone; on the CSTR that
episode had no violation while theta0's expected violation is about 6, the budget (0.1) then
excluded every theta including theta0's neighbours, and the learner re-ran theta0.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from mpcmobo.bo.context import expected_outcome_means, expected_outcome_samples, with_contexts
from mpcmobo.bo.surrogate import GPSurrogate
from mpcmobo.learners.base import check_choice
from mpcmobo.rl.judge import check_confidence

BUDGET_FACTOR = 2.0  # default budget: this multiple of theta0's own violation (+ floor)
# deploy_paired (session 9): how a candidate's own episodes must compare with the deployed
# theta's prediction at their starts: "every" one better, plus pointwise dominance (the rule of
# session 5), or "mean": better on average with deploy_confidence (paired_confidence); session
# 10, "cost": better on average in the episode cost itself (not its log), each episode against
# the deployed theta's own episodes from the same cycled start (J is a mean of costs); session
# 11: with random starts, "cost" compares the two thetas' own episode costs unpaired
# (unpaired_confidence, a Welch t-test), where it asked the model before
PAIRED_MODES = ("every", "mean", "cost")
# deploy_adjust (session 13): the unpaired test of random starts on the costs as they are
# ("none", unpaired_confidence) or adjusted for each episode's start covariate ("start_cost",
# adjusted_confidence: theta0's cost from that start on the MPC's own model)
ADJUST_MODES = ("start_cost", "none")
# deploy_screen (session 14): below deploy_min_runs a side, a candidate is screened by the test
# itself ("test") or on its cost relative to its starts ("relative", relative_screen); session
# 16, "first": relatively only while a side has a single episode (where the test has no
# degrees of freedom and compares raw costs), by the test from two a side
SCREEN_MODES = ("test", "relative", "first")
# deploy_baseline (session 16): the deployed theta is run again to match a verified candidate
# ("verify"), or also alternating with the search until it has deploy_min_runs ("early")
BASELINE_MODES = ("verify", "early")
# deploy_coverage (session 17): under cycled starts a candidate's evidence counted in matched
# episodes ("episodes": seven episodes from four of six starts were enough, and a start that
# carries most of the cost could be missing) or in distinct matched starts ("starts": with
# deploy_min_runs the cycle's length, a candidate is deployed only once run from every start); the
# default since session 18
COVERAGE_MODES = ("episodes", "starts")


@dataclass(frozen=True)
class Decision:
    """The outcome of the deployment rule after a fit: the deployed theta (unit cube), a
    candidate to run again as a verification episode (None: nothing to verify), and the best
    safe candidate if it is more likely better than the deployed theta than not (None: no
    such candidate, or it was deployed; the centre of the trust region with
    ``trust_center = "candidate"``)."""

    deployed: np.ndarray
    verify: np.ndarray | None = None
    candidate: np.ndarray | None = None  # the best safe candidate when promising (P >= 0.5)


def theta_key(z: np.ndarray) -> bytes:
    """Identity of a unit-cube theta up to the round trip through theta (1e-9)."""
    return np.round(np.asarray(z, float), 9).tobytes()


@dataclass(frozen=True)
class DeployRule:
    """Options of the deployment and safety rules (see the module docstring).

    ``min_runs`` (``deploy_min_runs``): a candidate is deployed only once it has been run on at
    least that many starts; a promising candidate with fewer runs (more likely better than the
    deployed theta than not) is proposed again, as a verification episode. ``shortlist``: the
    number of best candidates by the cheap first pass (posterior means,
    :func:`~mpcmobo.bo.context.expected_outcome_means`) that are judged by joint samples.
    """

    kappa: float = 1.0
    deploy_confidence: float | None = None
    safety_confidence: float = 0.9
    n_samples: int = 128
    min_runs: int = 1
    shortlist: int = 8
    max_runs: int | None = None
    paired_mode: str = "every"
    model_confidence: float | None = None  # the GP's P(better) to deploy (None: deploy_confidence)

    @property
    def run_cap(self) -> int:
        """Episodes a candidate may get before it must convince (``max_runs``; None:
        ``min_runs``): a candidate with ``min_runs`` episodes that is more likely better than
        the deployed theta than not, but not yet with ``deploy_confidence``, is run again up
        to this many times."""
        return self.min_runs if self.max_runs is None else max(self.min_runs, self.max_runs)

    def __post_init__(self) -> None:
        if self.deploy_confidence is not None:
            check_confidence(
                "deploy_confidence", self.deploy_confidence, ", or 0 or unset (the old rule)"
            )
        check_confidence("safety_confidence", self.safety_confidence)
        if self.min_runs < 1:
            raise ValueError(f"deploy_min_runs must be at least 1, got {self.min_runs}")
        if self.max_runs is not None and self.max_runs < 1:
            raise ValueError(f"deploy_max_runs must be at least 1, got {self.max_runs}")
        check_choice("deploy_paired", self.paired_mode, PAIRED_MODES)
        if self.model_confidence is not None:
            check_confidence("deploy_model_confidence", self.model_confidence, " or unset")

    def safe(self, samples: np.ndarray, budget: float | None) -> np.ndarray:
        """(n,) True where the expected violation's upper quantile is within the budget
        (``samples`` (S, n, m): the violation is the last column)."""
        if budget is None:
            return np.ones(samples.shape[1], dtype=bool)
        ucb = np.quantile(samples[:, :, -1], self.safety_confidence, axis=0)
        return ucb <= budget

    def score(self, samples: np.ndarray) -> np.ndarray:
        """Risk-averse score of the expected f1 (first column): mean + kappa std."""
        f1 = samples[:, :, 0]
        return f1.mean(axis=0) + self.kappa * f1.std(axis=0)

    def shortlisted(
        self,
        surrogate: GPSurrogate,
        Z: np.ndarray,
        current: np.ndarray,
        contexts: np.ndarray,
        budget: float | None,
    ) -> np.ndarray:
        """The cheap first pass: the ``shortlist`` rows of ``Z`` with the lowest expected f1
        (posterior means) among those not surely unsafe, and ``current``."""
        E, U = expected_outcome_means(
            surrogate, Z, contexts, quantile=None if budget is None else 0.5
        )
        score = E[:, 0].copy()
        if budget is not None:  # the median bound: points far over the budget drop out here
            score[U[:, -1] > budget] = np.inf  # type: ignore[index]  # a quantile was asked
        keep = np.argsort(score, kind="stable")[: self.shortlist]
        keep = keep[np.isfinite(score[keep])]
        return np.unique(np.vstack([Z[keep], current[None, :]]), axis=0)

    def choose(
        self,
        surrogate: GPSurrogate,
        Z: np.ndarray,
        current: np.ndarray,
        contexts: np.ndarray,
        budget: float | None,
        seed: int,
    ) -> np.ndarray:
        """The deployed unit-cube theta after a fit: ``current`` unless a safe observed theta
        in ``Z`` is confidently better (or ``deploy_confidence`` is None: the best safe one);
        :meth:`decide` without ``min_runs`` and the paired check."""
        rule = self if self.min_runs == 1 else replace(self, min_runs=1)
        return rule.decide(surrogate, Z, current, contexts, budget, seed).deployed

    def decide(
        self,
        surrogate: GPSurrogate,
        Z: np.ndarray,
        current: np.ndarray,
        contexts: np.ndarray,
        budget: float | None,
        seed: int,
        runs: Callable[[np.ndarray], int] | None = None,
        paired: Any = None,
    ) -> Decision:
        """:meth:`choose` with the evidence rules: the deployed theta and a candidate to verify.

        ``runs(z) -> int``: how many episodes ``z`` has had (for ``min_runs``);
        ``paired(z, current)``: the like-for-like check on ``z``'s own episodes (each
        observed cost against ``current``'s prediction at the same start). With
        ``paired_mode = "every"`` it returns a bool (``z`` did better in every episode) and a
        candidate is deployed only if it also :meth:`dominates`; with ``"mean"`` or ``"cost"``
        (the learner's paired check decides the units) it returns
        the confidence that ``z`` is better on average over its episodes' own starts
        (:func:`paired_confidence`), a candidate needs 0.5 to be considered and
        ``deploy_confidence`` to be deployed, the deployed theta itself ``min_runs``
        episodes, and the pointwise dominance is not required.
        Candidates that fail the check are not considered (neither deployed nor verified).
        Both optional.
        """
        Z = np.unique(np.atleast_2d(Z), axis=0)
        if len(Z) == 0:
            return Decision(current)
        if self.deploy_confidence is not None and len(Z) > self.shortlist:
            Z = self.shortlisted(surrogate, Z, current, contexts, budget)
        evidence: dict[bytes, float] = {}
        if self.deploy_confidence is not None and paired is not None:
            if self.paired_mode == "every":
                # a candidate one of whose own episodes did worse than the deployed theta
                # would have done from the same start is out: one bad start is evidence enough
                keep = [theta_key(z) == theta_key(current) or paired(z, current) for z in Z]
            else:  # "mean" / "cost": the candidate's episodes, matched, better on average
                for z in Z:
                    if theta_key(z) != theta_key(current):
                        evidence[theta_key(z)] = float(paired(z, current))
                keep = [evidence.get(theta_key(z), 1.0) >= 0.5 for z in Z]
            Z = Z[np.asarray(keep, dtype=bool)]
            if len(Z) == 0:
                return Decision(current)
        S = expected_outcome_samples(surrogate, Z, contexts, n_samples=self.n_samples, seed=seed)
        ok = self.safe(S, budget)
        if not ok.any():
            return Decision(current)
        score = np.where(ok, self.score(S), np.inf)
        best = Z[int(np.argmin(score))]
        if theta_key(best) == theta_key(current):
            return Decision(current)
        if self.deploy_confidence is None:
            return Decision(best.copy())
        J = expected_outcome_samples(
            surrogate,
            np.vstack([best, current]),
            contexts,
            n_samples=4 * self.n_samples,
            seed=seed + 1,
            joint=True,
        )[:, :, 0]
        p = float(np.mean(J[:, 0] < J[:, 1]))
        n_runs = self.min_runs if runs is None else int(runs(best))
        promising = best.copy() if p >= 0.5 else None
        if n_runs < self.min_runs:  # promising but not yet replicated: run it again
            return Decision(current, promising, promising)
        if self.paired_mode != "every" and paired is not None:
            # both sides of the comparison need evidence: the deployed theta's own episodes
            # anchor the model's prediction of it at the candidate's starts
            convinced = evidence[theta_key(best)] >= self.deploy_confidence and (
                runs is None or int(runs(current)) >= self.min_runs
            )
        else:
            convinced = self.dominates(surrogate, best, current, contexts)
        need = self.deploy_confidence if self.model_confidence is None else self.model_confidence
        if p < need or not convinced:
            if p >= 0.5 and n_runs < self.run_cap:  # promising, not yet convincing: run again
                return Decision(current, best.copy(), promising)
            return Decision(current, None, promising)
        return Decision(best.copy())

    @staticmethod
    def dominates(
        surrogate: GPSurrogate, new: np.ndarray, current: np.ndarray, contexts: np.ndarray
    ) -> bool:
        """True when the posterior mean of f1 at ``new`` is no worse than at ``current`` from
        every one of the contexts: a theta better on average but predicted worse from some
        starts (on the CSTR: the lower steady-state branch) is not deployed."""
        C = np.asarray(contexts, float)
        if C.ndim != 2 or C.shape[1] == 0:
            return True
        K = len(C)
        mt, _ = surrogate.posterior_model_space(with_contexts(np.stack([new, current]), C))
        return bool(np.all(mt[:K, 0] >= mt[K:, 0]))  # model space is maximised


def paired_confidence(d: np.ndarray) -> float:
    """The confidence that a candidate is better than the deployed theta from its own
    episodes' starts: ``d`` (n,) the per-episode advantages (the deployed theta's predicted
    cost minus the candidate's observed cost, in the GP's log space, at the episode's own
    initial state; with ``deploy_paired = "cost"`` the deployed theta's observed mean cost
    from the same start minus the candidate's cost), the one-sided t-test of ``mean(d) > 0``: ``F_t(n-1)(mean / (sd /
    sqrt(n)))``. Scale-free (log costs) and it grows with evidence, where "better in every
    episode" falls with the number of episodes. One episode: 0.5 if it was better (enough to
    be verified, never to be deployed), else 0."""
    d = np.asarray(d, float)
    d = d[np.isfinite(d)]
    if len(d) == 0:
        return 0.0
    if len(d) == 1:
        return 0.5 if d[0] > 0 else 0.0
    from scipy.stats import t

    sd = float(np.std(d, ddof=1))
    mean = float(np.mean(d))
    if sd == 0:
        return 1.0 if mean > 0 else 0.0
    return float(t.cdf(mean / (sd / np.sqrt(len(d))), df=len(d) - 1))


def unpaired_confidence(deployed: np.ndarray, candidate: np.ndarray) -> float:
    """The confidence that a candidate is better than the deployed theta when their episodes
    cannot be matched (random starts): ``deployed`` and ``candidate`` the episode costs of
    each, the one-sided Welch t-test of ``mean(deployed) > mean(candidate)``,
    ``F_t(nu)((mean(deployed) - mean(candidate)) / sqrt(s_d^2 / n_d + s_c^2 / n_c))`` with the
    Welch-Satterthwaite ``nu``. In the cost itself, as J(theta) = E_x0[f1] is a mean of costs;
    the spread of the starts is part of the standard error, so it asks for more episodes
    than the paired test of cycled starts. Fewer than two episodes on either side: 0.5 if
    the candidate's mean is lower (enough to be verified, never to be deployed), else 0."""
    d = np.asarray(deployed, float)
    c = np.asarray(candidate, float)
    d, c = d[np.isfinite(d)], c[np.isfinite(c)]
    if len(c) == 0 or len(d) == 0:
        return 0.0
    diff = float(np.mean(d) - np.mean(c))
    if len(c) < 2 or len(d) < 2:
        return 0.5 if diff > 0 else 0.0
    if np.var(d) + np.var(c) == 0:  # no spread on either side: scipy's statistic is undefined
        return 1.0 if diff > 0 else 0.0
    from scipy.stats import ttest_ind

    return 1.0 - float(ttest_ind(d, c, equal_var=False, alternative="greater").pvalue)


def _finite_episodes(
    deployed: np.ndarray, candidate: np.ndarray, s_deployed: np.ndarray, s_candidate: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The episodes of each side with a finite cost, each with its covariate (a failed
    episode is dropped with its start cost): ``y_d, y_c, s_d, s_c``."""
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
    r""":func:`unpaired_confidence` adjusted for how costly each episode's start was: the
    analysis of covariance of the episode costs ``y`` on the start covariate ``s`` (theta0's
    cost from the episode's start on the MPC's own model, ``EpisodeResult.start_cost``) with a
    common slope,

    .. math:: y_i = a + \delta\,[i \text{ is the candidate's}] + b\,s_i + e_i,

    and the one-sided t-test of ``delta < 0`` (the candidate cheaper at the same start) with
    ``n - 3`` degrees of freedom (:func:`ancova_confidence`). Under random starts the
    covariate is independent of which theta runs, so ``delta`` estimates the difference of
    the expected costs J, and the part of the spread the starts explain (on `lq` nearly all
    of it) leaves the test.

    No decision rests on one episode: the confidence is the smaller of the test on all
    episodes and the test without the episode of the highest leverage (the largest diagonal
    element of the hat matrix, ``1/n_g + (s_i - sbar_g)^2 / S_ss``). On the CSTR one hot-spot
    start of theta0 (cost 30 times the others, covariate 4 times) sets the slope, and a
    candidate that never met such a start is credited by extrapolation (session 13: 0.924 on
    all episodes, a theta 1.6 times worse than theta0 on fresh starts; 0.5 without that
    episode). Falls back to :func:`unpaired_confidence` when a covariate is missing (not
    finite), a side has fewer than two episodes, or the covariate has no spread within the
    groups."""
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


def relative_screen(
    deployed: np.ndarray,
    candidate: np.ndarray,
    s_deployed: np.ndarray,
    s_candidate: np.ndarray,
) -> float:
    r"""The screen of a candidate whose evidence is still short of the test's (random starts,
    fewer than ``deploy_min_runs`` episodes on a side): 0.5 when its cost relative to its
    starts, the ratio of means :math:`R = \sum_i y_i / \sum_i s_i`, is below the deployed
    theta's, else 0 -- enough to be run again, never to be deployed.

    :func:`adjusted_confidence` is the test for the decision; on two or three episodes its
    fitted intercept extrapolates between starts that do not overlap (session 14, `lq`: a
    candidate 3-7% cheaper relative to its two small starts scored 0.45 against theta0's two
    larger ones, at one degree of freedom, and was never run again), and the raw costs of
    :func:`unpaired_confidence` judge the starts' luck (a candidate run once from a costly
    start looked dearer than theta0, whatever its theta). The ratio of means is the cost
    model of a start that costs in proportion to its covariate, which the covariate is built
    to be (theta0's cost from that start); unlike the mean of the ratios it is not carried by
    a start near the equilibrium (a tiny ``s``). Without a positive covariate on every
    episode, the raw means."""
    y_d, y_c, s_d, s_c = _finite_episodes(deployed, candidate, s_deployed, s_candidate)
    if len(y_d) == 0 or len(y_c) == 0:
        return 0.0
    s_ok = np.all(np.isfinite(s_d)) and np.all(np.isfinite(s_c))
    if s_ok and np.all(s_d > 0) and np.all(s_c > 0):
        cand, dep = y_c.sum() / s_c.sum(), y_d.sum() / s_d.sum()
    else:
        cand, dep = y_c.mean(), y_d.mean()
    return 0.5 if cand < dep else 0.0


def ancova_confidence(
    y_d: np.ndarray, y_c: np.ndarray, s_d: np.ndarray, s_c: np.ndarray
) -> float | None:
    r"""The one-sided ANCOVA t-test of :func:`adjusted_confidence` on all the given episodes
    (finite costs): by least squares ``delta = (ybar_c - ybar_d) - b (sbar_c - sbar_d)``, ``b``
    the pooled within-group slope, ``se^2 = MSE (1 / n_c + 1 / n_d + (sbar_c - sbar_d)^2 /
    S_ss)``, ``F_t(n-3)(-delta / se)``. None where it is undefined: a covariate not finite, a
    side with fewer than two episodes, or no spread of the covariate within the groups."""
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
    from scipy.stats import t

    return float(t.cdf(-delta / np.sqrt(se2), df=dof))


def default_budget(theta0_violation: float, floor: float) -> float:
    """``BUDGET_FACTOR x`` theta0's (expected) violation plus ``floor`` (non-finite: floor)."""
    v = float(theta0_violation)
    return BUDGET_FACTOR * (v if np.isfinite(v) and v > 0 else 0.0) + float(floor)
