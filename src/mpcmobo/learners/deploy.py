"""Which theta a GP learner deploys: one policy object per rule, chosen when it is built.

The deployed theta is what the plant runs and what J_eval measures. A policy answers two
questions after every fit: which observed theta is deployed now, and which episode it wants
next to gather evidence (:meth:`DeployPolicy.decide`, :meth:`DeployPolicy.next_check`).

* :class:`CycledEvidence` (cycled starts): a candidate is deployed once it has been run from
  every start of the cycle and its episodes are cheaper than the deployed theta's own from
  the same starts (:func:`~mpcmobo.learners.confidence.paired_confidence`);
* :class:`RandomEvidence` (random starts): the two thetas' episode costs adjusted for their
  starts (:func:`~mpcmobo.learners.confidence.adjusted_confidence`), each side with
  ``min_runs`` episodes, and without a twin the candidate with ``2 min_runs``; the deployed
  theta is run again early, alternating with the search;
* :class:`Incumbent` (the paper's rule): the GP's best risk-averse observed point after every
  fit.

In both evidence policies the GP names the candidate (:func:`choose_candidate`): the observed
theta with the lowest ``mean + kappa std`` of its posterior f1 among those the evidence does
not rule out, which the GP must find more likely better than the deployed theta than not. A
theta with a failed episode (a cost that is not finite: the plant diverged) is never a
candidate, nor is a theta only simulated (a refused candidate's episode on the identified
model: the GP learns from it, the deployment never rests on it). Once a twin judges
(``twin``: identify-first, after the identified model is deployed), the test that deploys is the prediction-powered one
(:func:`~mpcmobo.learners.confidence.twin_confidence`): the same plant episodes, each with
the twin's prediction, and the twin's costs on its simulated starts.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from mpcmobo.bo import GPSurrogate, pareto_mask
from mpcmobo.learners.base import Starts
from mpcmobo.learners.confidence import adjusted_confidence, paired_confidence, relative_screen
from mpcmobo.learners.evidence import Evidence, theta_key
from mpcmobo.learners.judge import paired_differences, twin_verdict
from mpcmobo.learners.options import EvidenceDeploy, IncumbentDeploy
from mpcmobo.learners.prediction import Twin

__all__ = [
    "CycledEvidence",
    "Decision",
    "DeployPolicy",
    "EvidencePolicy",
    "Incumbent",
    "RandomEvidence",
    "choose_candidate",
    "make_policy",
]

SHORTLIST = 8  # candidates judged by posterior samples (the lowest posterior means)
N_SAMPLES = 128  # posterior samples of the candidates' f1
MODEL_CONFIDENCE = 0.5  # the GP's P(candidate better) needed to deploy: more likely than not


@dataclass(frozen=True)
class Decision:
    """The deployed theta after a fit (unit cube) and a candidate to run again (None: none)."""

    deployed: np.ndarray
    verify: np.ndarray | None = None


class DeployPolicy(Protocol):
    """What the GP learner asks of its deployment policy."""

    gathers_evidence: bool
    """Whether verification episodes are evidence (neither success nor failure of the trust
    region)."""
    relative: bool
    """Whether the GP models f1 relative to the episode's start cost."""
    uses_start_cost: bool
    """Whether episodes need their start cost (``EpisodeResult.start_cost``)."""

    def decide(
        self, ev: Evidence, surrogate: GPSurrogate, deployed: np.ndarray, seed: int
    ) -> Decision:
        """The deployed theta and a candidate to verify, after a fit on ``ev``."""

    def next_check(
        self, ev: Evidence, deployed: np.ndarray, verify: np.ndarray | None
    ) -> tuple[str, np.ndarray] | None:
        """The episode the policy wants next: ``("verify", z)``, ``("baseline", z)`` or None
        (the search proposes)."""


def cost_score(samples: np.ndarray, kappa: float) -> np.ndarray:
    """Risk-averse score of posterior samples (S, n) of a cost: ``mean + kappa std``."""
    return samples.mean(axis=0) + kappa * samples.std(axis=0)


def shortlisted(surrogate: GPSurrogate, Z: np.ndarray, current: np.ndarray) -> np.ndarray:
    """The unique observed thetas ``Z`` (unit cube) the GP judges: all of them, or above
    ``SHORTLIST`` the ``SHORTLIST`` of the lowest posterior mean f1 and ``current``."""
    Z = np.unique(np.atleast_2d(Z), axis=0)
    if len(Z) <= SHORTLIST:
        return Z
    mean, _ = surrogate.to_cost_space(*surrogate.posterior_model_space(Z))
    keep = np.argsort(mean[:, 0], kind="stable")[:SHORTLIST]
    keep = keep[np.isfinite(mean[keep, 0])]
    return np.unique(np.vstack([Z[keep], current[None, :]]), axis=0)


def choose_candidate(
    surrogate: GPSurrogate, Z: np.ndarray, current: np.ndarray, kappa: float, seed: int
) -> tuple[np.ndarray, float] | None:
    """The GP's candidate among the thetas ``Z`` (unit cube, :func:`shortlisted` and screened
    by the evidence) and the posterior probability that it is cheaper than ``current``; None
    when the best is ``current`` or ``Z`` is empty. The candidate has the lowest
    :func:`cost_score` of ``N_SAMPLES`` posterior samples of f1; the probability comes from
    ``4 N_SAMPLES`` joint samples of the two."""
    if len(Z) == 0:
        return None
    S = surrogate.cost_samples(Z, n_samples=N_SAMPLES, seed=seed)[:, :, 0]
    best = Z[int(np.argmin(cost_score(S, kappa)))]
    if theta_key(best) == theta_key(current):
        return None
    J = surrogate.cost_samples(
        np.vstack([best, current]), n_samples=4 * N_SAMPLES, seed=seed + 1, joint=True
    )[:, :, 0]
    return best.copy(), float(np.mean(J[:, 0] < J[:, 1]))


class EvidencePolicy:
    """The decision both evidence policies share; subclasses say how evidence is counted and
    judged (:meth:`runs`, :meth:`confidence`)."""

    gathers_evidence = True
    uses_start_cost = True
    relative = False
    paired = False  # the two thetas' episodes come from the same starts

    def __init__(self, confidence: float, min_runs: int, kappa: float) -> None:
        self.confidence = float(confidence)
        self.min_runs = int(min_runs)
        self.max_runs = 2 * self.min_runs
        self.kappa = float(kappa)
        self.twin: Twin | None = None  # the twin that judges (module docstring), if any

    def runs(self, ev: Evidence, z: np.ndarray, deployed: np.ndarray) -> int:
        """How much evidence ``z`` has (compared with ``min_runs``)."""
        raise NotImplementedError

    def confidence_of(
        self, ev: Evidence, surrogate: GPSurrogate | None, z: np.ndarray, deployed: np.ndarray
    ) -> float:
        """The confidence that ``z`` is cheaper than ``deployed``."""
        raise NotImplementedError

    def verdict(
        self, ev: Evidence, surrogate: GPSurrogate | None, z: np.ndarray, deployed: np.ndarray
    ) -> float:
        """The confidence a deployment rests on: the judge's twin test
        (:func:`~mpcmobo.learners.judge.twin_verdict`) on the two thetas' finite episodes
        once a twin judges, else :meth:`confidence_of`."""
        twin = self.twin
        if twin is None:
            return self.confidence_of(ev, surrogate, z, deployed)
        rows = (ev.rows_of(deployed), ev.rows_of(z))
        return twin_verdict(ev, twin, rows, (deployed, z), self.paired)

    def needed(self) -> int:
        """The candidate's evidence (:meth:`runs`) before it is judged."""
        return self.min_runs

    def next_check(
        self, ev: Evidence, deployed: np.ndarray, verify: np.ndarray | None
    ) -> tuple[str, np.ndarray] | None:
        """The episode the policy wants next (see :class:`DeployPolicy`)."""
        raise NotImplementedError

    def decide(
        self, ev: Evidence, surrogate: GPSurrogate, deployed: np.ndarray, seed: int
    ) -> Decision:
        """The candidate (:func:`choose_candidate`) replaces ``deployed`` once it has the
        evidence :meth:`needed`, is cheaper with ``confidence`` (:meth:`verdict`) and the
        deployed theta has ``min_runs``; a promising one (GP probability >= 0.5) while either
        side has less evidence, or not yet convincing and below ``2 min_runs``, is to be run
        again. A theta with a failed episode is never the candidate."""
        key_now = theta_key(deployed)
        ruled_out = ev.failed() - {key_now}
        ran = ev.Z[ev.finite() & ev.plant()]  # a simulated theta is no candidate
        Zf = np.array([z for z in ran if theta_key(z) not in ruled_out])
        if len(Zf) == 0:
            return Decision(deployed)
        Z = shortlisted(surrogate, Zf, deployed)
        screen = {
            theta_key(z): self.confidence_of(ev, surrogate, z, deployed)
            for z in Z
            if theta_key(z) != key_now
        }
        Z = Z[[theta_key(z) == key_now or screen[theta_key(z)] >= 0.5 for z in Z]]
        found = choose_candidate(surrogate, Z, deployed, self.kappa, seed)
        if found is None:
            return Decision(deployed)
        best, p = found
        n_runs = self.runs(ev, best, deployed)
        promising = best if p >= 0.5 else None
        if n_runs < self.needed() or self.runs(ev, deployed, deployed) < self.min_runs:
            return Decision(deployed, promising)
        convinced = (
            p >= MODEL_CONFIDENCE and self.verdict(ev, surrogate, best, deployed) >= self.confidence
        )
        if not convinced:
            if p >= 0.5 and n_runs < self.max_runs:
                return Decision(deployed, best)
            return Decision(deployed)
        return Decision(best)


class CycledEvidence(EvidencePolicy):
    """Paired evidence over every start of a cycle of ``n_starts`` (module docstring)."""

    paired = True

    def __init__(self, n_starts: int, confidence: float, kappa: float) -> None:
        super().__init__(confidence, n_starts, kappa)

    def runs(self, ev: Evidence, z: np.ndarray, deployed: np.ndarray) -> int:
        """The distinct starts of ``z``'s episodes that ``deployed`` was run from too, until
        that is every start of the cycle; then the number of those matched episodes."""
        own = ev.starts_of(deployed)
        matched = [int(ev.starts[i]) for i in ev.rows_of(z) if int(ev.starts[i]) in own]
        covered = len(set(matched))
        return covered if covered < self.min_runs else len(matched)

    def confidence_of(
        self, ev: Evidence, surrogate: GPSurrogate | None, z: np.ndarray, deployed: np.ndarray
    ) -> float:
        """Each episode of ``z`` against the mean cost of ``deployed``'s own episodes from the
        same start, paired (:func:`~mpcmobo.learners.confidence.paired_confidence`); without a
        matched start, its episodes against the GP's prediction of ``deployed`` (model space,
        start offset removed), or 0 without a GP."""
        rows = ev.rows_of(z)
        own = ev.rows_of(deployed)
        d = paired_differences(ev.Y[:, 0], ev.starts, rows, own, per="episode")
        if len(d):
            return paired_confidence(d)
        if not len(rows) or surrogate is None:
            return 0.0
        t_obs = surrogate.to_model_space(ev.Y[rows])[:, 0]
        t_obs = t_obs - surrogate.start_offsets(ev.starts[rows])[:, 0]
        mt, _ = surrogate.posterior_model_space(np.repeat(deployed[None, :], len(rows), axis=0))
        return paired_confidence(t_obs - mt[:, 0])

    def next_check(
        self, ev: Evidence, deployed: np.ndarray, verify: np.ndarray | None
    ) -> tuple[str, np.ndarray] | None:
        """A candidate to verify runs from the next start of the cycle if the deployed theta
        was run from it, else the deployed theta runs there first ("baseline")."""
        if verify is None:
            return None
        nxt = (int(ev.starts[-1]) + 1) % self.min_runs
        if nxt not in ev.starts_of(deployed):
            return "baseline", deployed.copy()
        return "verify", verify


class RandomEvidence(EvidencePolicy):
    """Start-adjusted unpaired evidence under random starts (module docstring)."""

    relative = True

    def runs(self, ev: Evidence, z: np.ndarray, deployed: np.ndarray) -> int:
        """The finite episodes of ``z``."""
        return ev.runs(z)

    def confidence_of(
        self, ev: Evidence, surrogate: GPSurrogate | None, z: np.ndarray, deployed: np.ndarray
    ) -> float:
        """The two thetas' episode costs adjusted for their start costs
        (:func:`~mpcmobo.learners.confidence.adjusted_confidence`); while a side has a single
        episode, the relative screen."""
        rows, own = ev.rows_of(z), ev.rows_of(deployed)
        judge = relative_screen if min(len(own), len(rows)) < 2 else adjusted_confidence
        S = ev.start_costs
        return judge(ev.Y[own, 0], ev.Y[rows, 0], S[own], S[rows])

    def needed(self) -> int:
        """``min_runs`` once a twin judges; without one, ``2 min_runs``, judged once.

        The GP picks the candidate among many thetas for its cheap episodes, and under random
        starts a few cheap starts in a row are luck the start covariate does not see: on the
        noisy CSTR, where a theta's costliest starts cost 20 to 40 times the others, the test
        on six episodes a side deployed thetas 17-51% dearer than theta0 on four of 40 jobs.
        With the twin, its simulated starts carry the costly starts instead."""
        return self.min_runs if self.twin is not None else self.max_runs

    def next_check(
        self, ev: Evidence, deployed: np.ndarray, verify: np.ndarray | None
    ) -> tuple[str, np.ndarray] | None:
        """A candidate to verify runs again once the deployed theta has as many episodes (up
        to ``2 min_runs``), the deployed theta first otherwise; with none, the deployed theta
        runs again, alternating with the search, until it has ``min_runs`` episodes."""
        own = ev.runs(deployed)
        if verify is not None:
            if own < min(ev.runs(verify), self.max_runs):
                return "baseline", deployed.copy()
            return "verify", verify
        last = ev.kinds[-1] if ev.kinds else ""
        if last != "baseline" and own < self.min_runs:
            return "baseline", deployed.copy()
        return None


class Incumbent:
    """The paper's rule: after every fit the observed theta whose posterior mean is
    Pareto-optimal (one objective: any) with the lowest ``mean + kappa std`` of the modelled
    f1 (in the GP's model space)."""

    gathers_evidence = False
    uses_start_cost = False
    relative = False

    def __init__(self, kappa: float) -> None:
        self.kappa = float(kappa)

    def decide(
        self, ev: Evidence, surrogate: GPSurrogate, deployed: np.ndarray, seed: int
    ) -> Decision:
        """The incumbent among the finite observations of the plant."""
        Zf = ev.Z[ev.finite() & ev.plant()]
        mt, st = surrogate.posterior_model_space(Zf)
        mean, _ = surrogate.to_cost_space(mt, st)
        cand = np.flatnonzero(pareto_mask(mean)) if mean.shape[1] > 1 else np.arange(len(Zf))
        score = -mt[:, 0] + self.kappa * st[:, 0]  # model space is maximised: -mt
        return Decision(Zf[int(cand[int(np.argmin(score[cand]))])].copy())

    def next_check(
        self, ev: Evidence, deployed: np.ndarray, verify: np.ndarray | None
    ) -> tuple[str, np.ndarray] | None:
        """Nothing: the incumbent rule never asks for an episode."""
        return None


def evidence_policy(deploy: EvidenceDeploy, starts: Starts, kappa: float) -> EvidencePolicy:
    """The evidence policy of the study's start design."""
    if starts.mode == "cycle":
        return CycledEvidence(starts.n_starts, deploy.confidence, kappa)
    return RandomEvidence(deploy.confidence, deploy.min_runs, kappa)


def make_policy(
    deploy: EvidenceDeploy | IncumbentDeploy, starts: Starts, kappa: float
) -> DeployPolicy:
    """The policy of the option ``deploy`` for the study's start design."""
    if isinstance(deploy, IncumbentDeploy):
        return Incumbent(kappa)
    return evidence_policy(deploy, starts, kappa)
