"""``deploy = "verified"`` (issue 11 item 3, session 8): on the default search of bo, mobo and
hybrid, a candidate becomes the deployed theta only after ``deploy_min_runs`` (2) episodes,
each better than the deployed theta would have been from the same start, and with
``P(J(new) < J(current)) >= deploy_confidence`` (0.9) under the GP.

The rule's decision on constructed data (a candidate seen once is verified, not deployed; seen
on two starts and better, it is deployed; a candidate that lost once is not); verification
episodes are not failures of the trust region; exact resume with the new state and old states
resuming with the rule they were made with; bad option values refused by name.
"""

from __future__ import annotations

import numpy as np
import pytest

from mpcmobo.learners import EpisodeResult, make_learner
from mpcmobo.learners.bo import _DefaultStr
from mpcmobo.learners.deploy import DeployRule
from mpcmobo.learners.registry import LearnerOptionError
from mpcmobo.systems import get_system

FAST = {"n_init": 3, "num_restarts": 2, "raw_samples": 32, "maxiter": 20}
OFFSETS = (0.0, 1.0, -1.0, 0.5, -0.5)  # log-cost effect of the cycled starts


@pytest.fixture(scope="module")
def lq():
    s = get_system("lq")
    return s.search_space, s.parameterization.theta0


def _cost(z, z0, start, rng=None):
    """exp(start effect) x a cost that falls along the first coordinate away from theta0."""
    noise = 0.0 if rng is None else 0.01 * rng.normal()
    return float(np.exp(OFFSETS[start] - 2.0 * (z[0] - z0[0]) + noise))


def _observe(learner, space, z, start, z0, rng=None):
    theta = space.from_unit(z, base=learner.theta0)
    f = np.array([_cost(z, z0, start, rng), 1.0, 0.0, 0.0])
    res = EpisodeResult(f, np.zeros(space.n_theta), True, start_id=start)
    learner.observe(theta, res)


def _key(z):
    return np.round(np.asarray(z, float), 9).tobytes()


def test_a_candidate_seen_once_is_verified_and_deployed_only_on_evidence(lq):
    """theta0 run from the three starts, a worse point, then a better candidate: after its
    first episode it is proposed again (a verification), not deployed; after a second start on
    which it is better too, it is deployed. The incumbent rule (the default) deploys it at once."""
    space, theta0 = lq
    z0 = space.to_unit(theta0)
    good, bad = z0.copy(), z0.copy()
    good[0], bad[0] = z0[0] + 0.1, z0[0] - 0.1
    runs = {}
    for mode in ("verified", "incumbent"):
        lr = make_learner("bo", space, theta0, seed=0, deploy=mode, trust_region="off", **FAST)
        for s in range(3):
            _observe(lr, space, z0, s, z0)
        _observe(lr, space, bad, 0, z0)
        _observe(lr, space, good, 1, z0)
        runs[mode] = lr
    once = runs["verified"]
    np.testing.assert_array_equal(once.incumbent(), theta0)  # seen once: not deployed
    np.testing.assert_allclose(space.to_unit(once.propose()), good)  # but run again
    assert once.proposal_kinds_[-1] == "verify"
    _observe(once, space, good, 2, z0)  # better on a second start
    np.testing.assert_allclose(space.to_unit(once.incumbent()), good)
    # the old rule deployed it after one episode
    np.testing.assert_allclose(space.to_unit(runs["incumbent"].incumbent()), good)


def test_the_deployed_theta_is_run_where_it_lacks_a_start_to_compare_with(lq):
    """Cycled starts: a promising candidate is run again only from a start the deployed theta
    was run from too; before that, the deployed theta itself is run ("baseline") from the next
    start. Only those like-for-like episodes count towards deploy_min_runs."""
    space, theta0 = lq
    z0 = space.to_unit(theta0)
    good, bad = z0.copy(), z0.copy()
    good[0], bad[0] = z0[0] + 0.1, z0[0] - 0.1
    lr = make_learner("bo", space, theta0, seed=0, deploy="verified", trust_region="off", **FAST)
    _observe(lr, space, z0, 0, z0)
    _observe(lr, space, bad, 1, z0)
    _observe(lr, space, good, 2, z0)  # theta0 was not run from start 2: no match yet
    assert lr._matched_runs(good) == 0 and _key(lr._verify_z) == _key(good)
    np.testing.assert_array_equal(lr.propose(), theta0)  # the next start, 3, for theta0
    assert lr.proposal_kinds_[-1] == "baseline"
    _observe(lr, space, z0, 3, z0)
    np.testing.assert_array_equal(lr.incumbent(), theta0)
    np.testing.assert_array_equal(lr.propose(), theta0)  # and 4 (the candidate is still unmatched)
    lr.proposal_kinds_.pop()
    _observe(lr, space, z0, 4, z0)
    _observe(lr, space, z0, 0, z0)  # the cycle wraps: 5 starts, the next is 1
    assert lr._next_start() == 1
    assert lr.proposal_kinds_ == ["baseline"]


def test_a_candidate_that_did_worse_from_one_start_is_not_deployed(lq):
    """Three episodes of the candidate, far better than theta0 from two starts and a little
    worse (30%) from the third (the paired check): not deployed, whatever the GP's average says.
    Without the third episode it is deployed."""
    space, theta0 = lq
    z0 = space.to_unit(theta0)
    good = z0.copy()
    good[0] = z0[0] + 0.1
    theta = space.from_unit(good, base=theta0)
    deployed = {}
    for third in (False, True):
        lr = make_learner("bo", space, theta0, seed=0, deploy="verified", trust_region="off",
                          deploy_min_runs=2 + third, **FAST)  # fmt: skip
        for s in range(3):
            _observe(lr, space, z0, s, z0)
        for s in (0, 1) + ((2,) if third else ()):
            f1 = _cost(z0, z0, s) * (1.3 if s == 2 else 0.5)  # 30% worse from start 2
            lr.observe(theta, EpisodeResult(np.array([f1, 1, 0, 0]), np.zeros(space.n_theta),
                                            True, start_id=s))  # fmt: skip
        deployed[third] = space.to_unit(lr.incumbent())
    np.testing.assert_allclose(deployed[False], good)
    np.testing.assert_array_equal(deployed[True], z0)


def test_decide_runs_a_promising_candidate_again_up_to_max_runs():
    """A candidate with min_runs episodes, more likely better than not but below
    deploy_confidence, is run again while it has fewer than max_runs (None: min_runs, the
    safe path's rule before session 8)."""
    from mpcmobo.bo import GPSurrogate

    rng = np.random.default_rng(0)
    X = rng.uniform(size=(12, 1))
    y = 1.0 + 0.05 * X[:, 0] + 0.05 * rng.normal(size=12)  # a weak slope: not confident
    sur = GPSurrogate(1).fit(X, y[:, None])
    lo, hi = np.array([0.05]), np.array([0.95])
    Z = np.vstack([lo, hi])
    strict = DeployRule(kappa=0.0, deploy_confidence=0.999, min_runs=2)
    assert strict.decide(sur, Z, hi, np.zeros((1, 0)), None, 0, runs=lambda z: 2).verify is None
    again = DeployRule(kappa=0.0, deploy_confidence=0.999, min_runs=2, max_runs=4)
    d = again.decide(sur, Z, hi, np.zeros((1, 0)), None, 0, runs=lambda z: 3)
    np.testing.assert_array_equal(d.deployed, hi)
    np.testing.assert_array_equal(d.verify, lo)
    assert again.decide(sur, Z, hi, np.zeros((1, 0)), None, 0, runs=lambda z: 4).verify is None


def test_verification_episodes_are_not_failures_of_the_trust_region(lq):
    """The box follows the deployed theta: a search point that earns a verification, and the
    verification itself, leave the failure count alone; a plain worse point is a failure."""
    space, theta0 = lq
    z0 = space.to_unit(theta0)
    good, bad = z0.copy(), z0.copy()
    good[0], bad[0] = z0[0] + 0.05, z0[0] - 0.05
    lr = make_learner("bo", space, theta0, seed=0, deploy="verified", **FAST)
    for s in range(3):
        _observe(lr, space, z0, s, z0)
    _observe(lr, space, bad, 0, z0)
    assert lr.trust_.failures == 1  # a worse point
    _observe(lr, space, good, 1, z0)
    assert lr._verify_z is not None and _key(lr._verify_z) == _key(good)
    assert lr.trust_.failures == 1  # earned a verification: not a failure
    _observe(lr, space, good, 2, z0)
    assert _key(space.to_unit(lr.incumbent())) == _key(good)
    assert lr.trust_.failures == 0 and lr.trust_.successes == 1  # deployed: a success


@pytest.mark.parametrize("name", ["bo", "hybrid"])
def test_verified_rule_resumes_exactly(lq, name):
    """The state after a search point that earned a verification (the pending verification is
    not saved: the replayed fit finds it again) resumes into the same proposals and deployed
    theta; the rule is saved with the state."""
    space, theta0 = lq
    z0 = space.to_unit(theta0)
    a = make_learner(name, space, theta0, seed=2, deploy="verified", **FAST)
    rng = np.random.default_rng(3)
    states = []
    for k in range(9):
        th = a.propose()
        _observe(a, space, space.to_unit(space.clip(th)), k % 3, z0, rng)
        if a._verify_z is not None:
            states.append((a.state_dict(), a._verify_z.copy(), a._verification()))
    assert states, "no verification was asked for"
    state, pending, (kind, z) = states[0]
    assert state["deploy"] == "verified"
    b = make_learner(name, space, theta0, seed=99, deploy="verified", **FAST)
    b.load_state_dict(state)
    np.testing.assert_array_equal(b._verify_z, pending)
    np.testing.assert_allclose(space.to_unit(space.clip(b.propose())), z, atol=1e-12)
    assert b.proposal_kinds_[-1] == kind
    last = make_learner(name, space, theta0, seed=99, deploy="verified", **FAST)
    last.load_state_dict(a.state_dict())
    np.testing.assert_array_equal(last.incumbent(), a.incumbent())
    np.testing.assert_array_equal(last.propose(), a.propose())
    assert last.trust_ == a.trust_


def test_states_resume_with_the_rule_they_were_made_with(lq):
    """A learner whose option is left at its (marked) default continues a run with the rule
    the run was made with: a state without "deploy" (before session 8) with the incumbent
    rule, one with "verified" with that; an explicit option is kept."""
    space, theta0 = lq
    z0 = space.to_unit(theta0)
    a = make_learner("bo", space, theta0, seed=0, deploy="verified", **FAST)
    for s in range(4):
        _observe(a, space, z0 if s < 3 else z0 * 0.9, s % 3, z0)
    state = a.state_dict()
    marked = make_learner("bo", space, theta0, seed=0, deploy=_DefaultStr("incumbent"), **FAST)
    marked.load_state_dict(state)
    assert marked.deploy == "verified" and marked.deploy_rule.min_runs == 2
    old = {k: v for k, v in state.items() if k != "deploy"}
    flipped = make_learner("bo", space, theta0, seed=0, deploy=_DefaultStr("verified"), **FAST)
    flipped.load_state_dict(old)
    assert flipped.deploy == "incumbent" and not flipped.safe_mode
    explicit = make_learner("bo", space, theta0, seed=0, deploy="verified", **FAST)
    explicit.load_state_dict(old)
    assert explicit.deploy == "verified"


def test_defaults_and_bad_values(lq):
    space, theta0 = lq
    plain = make_learner("mobo", space, theta0)
    assert plain.deploy == "incumbent" and not plain.safe_mode
    v = make_learner("mobo", space, theta0, deploy="verified")
    assert not v.safe_mode  # the default search: only the deployment changes
    assert (v.deploy_rule.deploy_confidence, v.deploy_rule.min_runs) == (0.9, 2)
    assert v.deploy_rule.run_cap == 4
    v3 = make_learner("bo", space, theta0, deploy="verified", deploy_min_runs=3,
                      deploy_confidence=0.95, deploy_max_runs=5)  # fmt: skip
    assert (v3.deploy_rule.deploy_confidence, v3.deploy_rule.min_runs) == (0.95, 3)
    assert v3.deploy_rule.run_cap == 5 and not v3.safe_mode
    with pytest.raises(LearnerOptionError, match="deploy must be one of 'incumbent', 'verified'"):
        make_learner("bo", space, theta0, deploy="yes")
    with pytest.raises(LearnerOptionError, match="deploy_max_runs must be an integer >= 1"):
        make_learner("hybrid", space, theta0, deploy="verified", deploy_max_runs=0)
    with pytest.raises(LearnerOptionError, match="deploy_confidence must be in"):
        make_learner("bo", space, theta0, deploy="verified", deploy_confidence=1.0)
    with pytest.raises(ValueError, match="deploy_max_runs must be at least 1"):
        DeployRule(max_runs=0)
