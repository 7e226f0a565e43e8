"""``deploy = "auto"`` under random starts (issue 11, session 11): no two episodes share a
start, so a candidate's episode costs are compared with the deployed theta's own episode costs
unpaired, by a one-sided Welch t-test in the cost itself
(:func:`~mpcmobo.learners.deploy.unpaired_confidence`), each side with at least
``deploy_min_runs`` (6) episodes; the deployed theta is run again ("baseline") while it has
fewer episodes than the candidate. Checked: the test statistic against scipy's own Welch test,
the resolution of "auto", the baseline episodes, a candidate cheaper on average deployed and
one cheaper typically but dearer on average (a heavy tail) refused, exact resume, and a
checkpoint from before session 11 resuming with the incumbent rule.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from mpcmobo.learners import EpisodeResult, make_learner
from mpcmobo.learners.bo import RANDOM_MIN_RUNS
from mpcmobo.learners.deploy import unpaired_confidence
from mpcmobo.systems import get_system

FAST = {"n_init": 3, "num_restarts": 2, "raw_samples": 32, "maxiter": 20}


@pytest.fixture(scope="module")
def lq():
    s = get_system("lq")
    return s.search_space, s.parameterization.theta0


def _observe(lr, theta, f1):
    y = np.array([f1, 1.0, 0.0, 0.0])
    lr.observe(theta, EpisodeResult(y, np.zeros(len(theta)), True, start_id=-1))


@pytest.mark.parametrize("seed", range(5))
def test_unpaired_confidence_is_scipys_welch_test(seed):
    rng = np.random.default_rng(seed)
    d = np.exp(rng.normal(1.0, 1.0, size=6 + seed))
    c = np.exp(rng.normal(0.5, 0.8, size=4 + 2 * seed))
    ref = stats.ttest_ind(d, c, equal_var=False, alternative="greater").pvalue
    assert unpaired_confidence(d, c) == pytest.approx(1 - ref, rel=1e-9, abs=1e-12)


def test_unpaired_confidence_with_little_evidence():
    assert unpaired_confidence(np.array([2.0, 3.0]), np.array([1.0])) == 0.5  # verify, not deploy
    assert unpaired_confidence(np.array([2.0]), np.array([3.0, 1.0])) == 0.0  # dearer
    assert unpaired_confidence(np.array([]), np.array([1.0, 2.0])) == 0.0
    assert unpaired_confidence(np.array([2.0, 2.0]), np.array([1.0, 1.0])) == 1.0
    assert unpaired_confidence(np.array([2.0, np.nan, 3.0]), np.array([1.0, 1.5])) > 0.9


def test_auto_under_random_starts(lq):
    space, theta0 = lq
    lr = make_learner("bo", space, theta0, seed=0, **FAST)
    _observe(lr, theta0, 1.0)
    assert (lr.deploy, lr.deploy_paired) == ("verified", "cost")
    assert (lr.deploy_rule.min_runs, lr.deploy_rule.run_cap) == (RANDOM_MIN_RUNS, 12)
    assert lr.deploy_rule.model_confidence == 0.5 and lr._unpaired_cost()
    assert not lr.safe_mode  # the default search; only the deployment changes


def _learner(lq, theta0_costs, cand_costs, **opts):
    """theta0's episodes, then a candidate 0.1 away (random starts, no trust region)."""
    space, theta0 = lq
    z0 = space.to_unit(theta0)
    good = z0.copy()
    good[0] = z0[0] + 0.1
    lr = make_learner("bo", space, theta0, seed=0, trust_region="off", **opts, **FAST)
    for f in theta0_costs:
        _observe(lr, theta0, f)
    for f in cand_costs:
        _observe(lr, space.from_unit(good, base=theta0), f)
    return lr, z0, good


THETA0 = np.array([1.0, 3.0, 0.5, 2.0, 8.0, 1.5])  # theta0's costs from six random starts


def test_cheaper_on_average_is_deployed(lq):
    lr, z0, good = _learner(lq, THETA0, 0.25 * THETA0[::-1])
    assert lr._paired_cost(good, z0) >= 0.9
    np.testing.assert_allclose(lr._incumbent_z, good)


def test_cheaper_typically_but_dearer_on_average_is_refused(lq):
    cand = np.array([0.3, 0.9, 0.2, 0.6, 0.4, 30.0])  # 5 of 6 below theta0's median, one tail
    assert np.median(cand) < np.median(THETA0) and cand.mean() > THETA0.mean()
    lr, z0, good = _learner(lq, THETA0, cand)
    assert lr._paired_cost(good, z0) < 0.5
    np.testing.assert_array_equal(lr._incumbent_z, z0)


def test_too_few_episodes_are_not_deployed(lq):
    """Five episodes of a much cheaper candidate: promising (verified), not deployed."""
    lr, z0, good = _learner(lq, THETA0, 0.1 * THETA0[:5])
    np.testing.assert_array_equal(lr._incumbent_z, z0)
    np.testing.assert_allclose(lr._verify_z, good)
    assert lr.propose() is not None and lr.proposal_kinds_[-1] == "verify"


def test_the_deployed_theta_is_run_as_a_baseline(lq):
    """theta0 run twice, a promising candidate three times: the next episode is theta0's."""
    space, theta0 = lq
    lr, z0, good = _learner(lq, THETA0[:2], [0.1, 0.2, 0.1])
    np.testing.assert_allclose(lr._verify_z, good)
    th = lr.propose()
    assert lr.proposal_kinds_[-1] == "baseline"
    np.testing.assert_allclose(space.to_unit(th), z0, atol=1e-12)


def test_auto_resumes_exactly_under_random_starts(lq):
    space, theta0 = lq
    a = make_learner("mobo", space, theta0, seed=2, **FAST)
    rng = np.random.default_rng(3)
    for _ in range(10):
        _observe(a, a.propose(), float(np.exp(rng.normal())))
    state = a.state_dict()
    assert state["random_rule"] == "welch"
    b = make_learner("mobo", space, theta0, seed=99, **FAST)
    b.load_state_dict(state)
    assert (b.deploy, b.deploy_paired, b.deploy_rule.min_runs) == ("verified", "cost", 6)
    np.testing.assert_array_equal(b.incumbent(), a.incumbent())
    np.testing.assert_array_equal(b.propose(), a.propose())
    assert b.proposal_kinds_[-1] == a.proposal_kinds_[-1]


def test_a_checkpoint_from_before_session_11_keeps_the_incumbent_rule(lq):
    """A learner state without "random_rule" (session 10: "auto" meant the incumbent rule
    under random starts) resumes with the incumbent rule."""
    space, theta0 = lq
    old = make_learner("bo", space, theta0, seed=0, **FAST)
    for f in (1.0, 2.0, 3.0):
        _observe(old, theta0, f)
    state = old.state_dict()
    state.pop("random_rule")
    state.update({"deploy": "incumbent", "deploy_paired": "every"})
    new = make_learner("bo", space, theta0, seed=0, **FAST)
    new.load_state_dict(state)
    _observe(new, space.from_unit(space.to_unit(theta0) * 0.95, base=theta0), 0.5)
    assert (new.deploy_option, new.deploy, new._random_rule) == ("auto", "incumbent", "legacy")
