"""``deploy_paired = "cost"`` (issue 11, session 10): under cycled starts, a candidate's
episodes are judged against the deployed theta's own episodes from the same starts on the
episode cost itself, by a one-sided t-test on the mean difference, instead of "better from
every start" (``deploy = "verified"``'s ``"every"``).

On `lq`'s search space with five cycled starts of different cost: a candidate much cheaper
from four starts and a little dearer from the cheapest one is refused by "every" and deployed
by "cost"; a candidate much cheaper from four starts and much dearer from the most expensive
one, cheaper in the mean of log costs but dearer in the mean of costs (what J measures), is
refused by "cost".
"""

from __future__ import annotations

import numpy as np
import pytest

from mpcmobo.learners import EpisodeResult, make_learner
from mpcmobo.learners.registry import LearnerOptionError
from mpcmobo.systems import get_system

FAST = {"n_init": 3, "num_restarts": 2, "raw_samples": 32, "maxiter": 20}
BASE = np.exp([0.0, 1.0, -1.0, 0.5, -0.5])  # theta0's cost from each of the 5 cycled starts


@pytest.fixture(scope="module")
def lq():
    s = get_system("lq")
    return s.search_space, s.parameterization.theta0


def _run(lq, paired, factors):
    """theta0 from the five starts, then a candidate 0.1 away from each start with cost
    ``factors[s] x`` theta0's; the learner (deploy = "verified", deploy_min_runs = 5)."""
    space, theta0 = lq
    z0 = space.to_unit(theta0)
    good = z0.copy()
    good[0] = z0[0] + 0.1
    lr = make_learner("bo", space, theta0, seed=0, deploy="verified", deploy_min_runs=5,
                      trust_region="off", deploy_paired=paired, **FAST)  # fmt: skip
    n = space.n_theta
    for theta, f in ((theta0, np.ones(5)), (space.from_unit(good, base=theta0), factors)):
        for s in range(5):
            y = np.array([BASE[s] * f[s], 1.0, 0.0, 0.0])
            lr.observe(theta, EpisodeResult(y, np.zeros(n), True, start_id=s))
    return lr, z0, good


def test_a_little_dearer_from_one_start_is_deployed_on_the_mean_cost(lq):
    factors = np.array([0.5, 0.5, 1.3, 0.5, 0.5])  # 30% dearer from the cheapest start
    every, z0, good = _run(lq, "every", factors)
    np.testing.assert_array_equal(every._incumbent_z, z0)  # one start lost: refused
    cost, z0, good = _run(lq, "cost", factors)
    assert cost._paired_cost(good, z0) >= 0.9
    np.testing.assert_allclose(cost._incumbent_z, good)


def test_cheaper_in_log_cost_but_dearer_on_average_is_not_deployed(lq):
    factors = np.array([0.3, 4.0, 0.3, 0.3, 0.3])  # 4x from the dearest start
    lr, z0, good = _run(lq, "cost", factors)
    saved = BASE * (1 - factors)
    assert np.mean(np.log(factors)) < 0 < -np.mean(saved)  # better typically, worse on average
    assert lr._paired_cost(good, z0) < 0.5
    np.testing.assert_array_equal(lr._incumbent_z, z0)


def test_unmatched_episodes_are_no_evidence(lq):
    """Episodes of the candidate from starts the deployed theta was not run from do not count:
    with theta0 run from start 0 only, the candidate's episodes from starts 1-4 are ignored."""
    space, theta0 = lq
    lr, z0, good = _run(lq, "cost", np.full(5, 0.5))
    assert lr._matched_runs(good) == 5
    only0 = make_learner("bo", space, theta0, seed=0, deploy="verified", deploy_min_runs=5,
                         trust_region="off", deploy_paired="cost", **FAST)  # fmt: skip
    only0.observe(theta0, EpisodeResult(np.array([1.0, 1, 0, 0]), np.zeros(space.n_theta),
                                        True, start_id=0))  # fmt: skip
    for s in range(1, 5):
        y = np.array([0.5 * BASE[s], 1.0, 0.0, 0.0])
        only0.observe(space.from_unit(good, base=theta0),
                      EpisodeResult(y, np.zeros(space.n_theta), True, start_id=s))  # fmt: skip
    assert only0._matched_runs(good) == 0
    np.testing.assert_array_equal(only0._incumbent_z, z0)


def test_unknown_paired_mode_is_refused_by_name(lq):
    space, theta0 = lq
    with pytest.raises((ValueError, LearnerOptionError), match="deploy_paired"):
        make_learner("bo", space, theta0, seed=0, deploy_paired="costs", **FAST)


def test_model_confidence_lets_the_paired_evidence_decide():
    """The GP only somewhat sure that ``lo`` beats ``hi`` (a weak slope) and the paired cost
    evidence strong (0.9999): with the GP held to deploy_confidence (0.999 here) ``hi``
    stays; with ``model_confidence = 0.5`` the evidence decides and ``lo`` is deployed; with
    weak evidence (0.6) it is not, whatever the model confidence."""
    from mpcmobo.bo import GPSurrogate
    from mpcmobo.learners.deploy import DeployRule

    rng = np.random.default_rng(0)
    X = rng.uniform(size=(12, 1))
    y = 1.0 + 0.05 * X[:, 0] + 0.05 * rng.normal(size=12)
    sur = GPSurrogate(1).fit(X, y[:, None])
    lo, hi = np.array([0.05]), np.array([0.95])
    Z, C = np.vstack([lo, hi]), np.zeros((1, 0))

    def deployed(model_confidence, evidence):
        rule = DeployRule(kappa=0.0, deploy_confidence=0.999, min_runs=2, paired_mode="cost",
                          model_confidence=model_confidence)  # fmt: skip
        d = rule.decide(sur, Z, hi, C, None, 0, runs=lambda z: 6, paired=lambda z, c: evidence)
        return d.deployed

    np.testing.assert_array_equal(deployed(None, 0.9999), hi)
    np.testing.assert_array_equal(deployed(0.5, 0.9999), lo)
    np.testing.assert_array_equal(deployed(0.5, 0.6), hi)
    with pytest.raises(ValueError, match="deploy_model_confidence"):
        DeployRule(deploy_confidence=0.9, model_confidence=0.3)
