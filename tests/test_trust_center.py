"""``trust_center = "candidate"`` (issue 11, session 9): under the safe design the trust region
is centred at the deployment rule's promising candidate, not only at the deployed theta, so
the search moves on with the evidence while the deployed theta waits for confidence.

On `lq`'s search space, with the deployment rule's verdict scripted (a candidate that is
promising and asked for verification, as :meth:`DeployRule.decide` returns it; the rule's own
statistics are tested in ``test_deploy_verified.py`` and ``test_context.py``): the box follows
the candidate while it is being verified, a verification it survives is neither a success nor
a failure of the box, proposals stay in the box around it, the deployed theta is not moved by
the centre, and the state resumes exactly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from mpcmobo.bo.context import ContextSpec
from mpcmobo.learners import EpisodeResult, make_learner
from mpcmobo.learners.deploy import Decision, DeployRule
from mpcmobo.learners.registry import LearnerOptionError
from mpcmobo.systems import get_system

FAST = {"n_init": 3, "num_restarts": 2, "raw_samples": 32, "maxiter": 20}
SAFE = {"context": "x0", "violation_budget": "auto", "deploy_confidence": 0.9}
TR = {"length_init": 0.1, "failure_tolerance": 4}


@pytest.fixture(scope="module")
def lq():
    s = get_system("lq")
    return s, s.search_space, s.parameterization.theta0, ContextSpec.from_system(s)


def _key(z):
    return np.round(np.asarray(z, float), 9).tobytes()


@dataclass(frozen=True)
class ScriptedRule(DeployRule):
    """The deployment rule's verdict, scripted: once ``good`` has been run it is the promising
    candidate, verified until it has ``min_runs`` episodes; the deployed theta stays."""

    good: np.ndarray | None = None

    def decide(self, surrogate, Z, current, contexts, budget, seed, runs=None, paired=None):
        seen = any(_key(z) == _key(self.good) for z in np.atleast_2d(Z))
        if not seen:
            return Decision(current)
        verify = self.good.copy() if runs(self.good) < self.min_runs else None
        return Decision(current, verify, self.good.copy())


def _learner(lq, centre, good, seed=0):
    s, space, theta0, spec = lq
    learner = make_learner(
        "mobo", space, theta0, seed=seed, contexts=spec, trust_region=TR,
        trust_center=centre, **SAFE, **FAST,
    )  # fmt: skip
    learner.deploy_rule = ScriptedRule(deploy_confidence=0.9, min_runs=3, good=good)
    return learner


def _observe(learner, lq, z, x0, factor):
    """One episode of ``z`` from ``x0``: a start-dependent cost times ``factor``."""
    s, space, theta0, _ = lq
    f1 = factor * float(np.exp(0.5 * np.sum(np.abs(x0))))
    res = EpisodeResult(
        np.array([f1, 1.0, 0.0, 0.0]), np.zeros(space.n_theta), True, x0=x0, violation=0.0
    )
    learner.observe(space.from_unit(z, base=theta0), res)


def _run(lq, centre):
    """theta0 from four starts, then a candidate 0.03 away, 10x better from every start, once;
    returns the learner and the candidate."""
    s, space, theta0, _ = lq
    z0 = space.to_unit(theta0)
    good = z0.copy()
    good[0] = z0[0] + 0.03
    learner = _learner(lq, centre, good)
    rng = np.random.default_rng(0)
    starts = [s.sample_initial_state(rng) for _ in range(8)]
    for k in range(4):
        learner.proposal_kinds_.append("design")
        _observe(learner, lq, z0, starts[k], 1.0)
    learner.proposal_kinds_.append("search")
    _observe(learner, lq, good, starts[4], 0.1)
    return learner, good, starts


def test_the_box_follows_the_promising_candidate_and_its_verification_is_neutral(lq):
    s, space, theta0, _ = lq
    z0 = space.to_unit(theta0)
    for centre in ("candidate", "deployed"):
        learner, good, starts = _run(lq, centre)
        # one episode: not yet deployed (deploy_min_runs = 3), run again as a verification
        assert _key(space.to_unit(learner.incumbent())) == _key(z0)
        assert learner._verify_z is not None and _key(learner._verify_z) == _key(good)
        lo, hi = learner._trust_box()
        expected = good if centre == "candidate" else z0
        np.testing.assert_allclose((lo + hi) / 2, expected, atol=1e-12)
        before = learner.trust_
        theta = learner.propose()
        assert learner.proposal_kinds_[-1] == "verify"
        np.testing.assert_allclose(space.to_unit(theta), good, atol=1e-12)
        _observe(learner, lq, good, starts[5], 0.1)
        if centre == "candidate":  # evidence gathered on the centre: the box is unchanged
            assert learner.trust_ == before
            assert _key(learner._candidate_z) == _key(good)
        else:  # the session-7 rule: not deployed, so a failure
            assert learner.trust_.failures == before.failures + 1


def test_a_search_proposal_lies_in_the_box_around_the_candidate(lq):
    s, space, theta0, _ = lq
    learner, good, starts = _run(lq, "candidate")
    learner._verify_z = None  # skip the verification: the next proposal is a search
    lo, hi = learner._trust_box()
    z = space.to_unit(learner.propose())
    assert learner.proposal_kinds_[-1] in ("search", "safe")
    assert np.all(z >= lo - 1e-9) and np.all(z <= hi + 1e-9)
    assert np.max(np.abs(z - good)) <= TR["length_init"] / 2 + 1e-9


def test_candidate_centre_resumes_exactly(lq):
    """A state saved right after a verification the candidate survived resumes into the same
    trust state and proposal (the centre before the last fit is part of the state)."""
    s, space, theta0, _ = lq
    learner, good, starts = _run(lq, "candidate")
    learner.propose()
    _observe(learner, lq, good, starts[5], 0.1)
    state = learner.state_dict()
    other = _learner(lq, "candidate", good, seed=7)
    other.load_state_dict(state)
    assert other.trust_ == learner.trust_
    np.testing.assert_array_equal(other._trust_box()[0], learner._trust_box()[0])
    np.testing.assert_array_equal(other.propose(), learner.propose())


def test_bad_value_is_refused(lq):
    s, space, theta0, spec = lq
    with pytest.raises(LearnerOptionError, match="trust_center must be one of"):
        make_learner("mobo", space, theta0, contexts=spec, trust_center="best")
