"""``deploy_paired = "cost"`` (issue 11, session 10): under cycled starts, a candidate's
episodes are judged against the deployed theta's own episodes from the same starts on the
episode cost itself, by a one-sided t-test on the mean difference, instead of "better from
every start" (``deploy = "verified"``'s ``"every"``).

On `lq`'s search space with five cycled starts of different cost: a candidate much cheaper
from four starts and a little dearer from the cheapest one is refused by "every" and deployed
by "cost"; a candidate much cheaper from four starts and much dearer from the most expensive
one, cheaper in the mean of log costs but dearer in the mean of costs (what J measures), is
refused by "cost".

``deploy = "auto"``, the default of bo, mobo and hybrid since session 10 (issue 11, item 3):
with cycled starts the rule above over the whole cycle (``deploy = "verified"``,
``deploy_paired = "cost"``, ``deploy_min_runs`` = the cycle's length, known after its first
wrap, ``deploy_model_confidence`` 0.5); with random starts (session 11) the unpaired cost
rule of ``tests/test_deploy_random.py``. Checked: the
resolution by start mode, options set by the user kept, the same decisions as the explicit
options, exact resume, and checkpoints from before "auto" resuming with their rule.
"""

from __future__ import annotations

import numpy as np
import pytest

from mpcmobo.learners import EpisodeResult, make_learner
from mpcmobo.learners.bo import CYCLE_UNKNOWN
from mpcmobo.learners.registry import LearnerOptionError
from mpcmobo.systems import get_system

FAST = {"n_init": 3, "num_restarts": 2, "raw_samples": 32, "maxiter": 20}
BASE = np.exp([0.0, 1.0, -1.0, 0.5, -0.5])  # theta0's cost from each of the 5 cycled starts


@pytest.fixture(scope="module")
def lq():
    s = get_system("lq")
    return s.search_space, s.parameterization.theta0


def _candidate(lq):
    """theta0 in the unit cube and a candidate 0.1 away from it in the first coordinate."""
    space, theta0 = lq
    z0 = space.to_unit(theta0)
    good = z0.copy()
    good[0] = z0[0] + 0.1
    return z0, good


def _run(lq, paired, factors):
    """theta0 from the five starts, then a candidate 0.1 away from each start with cost
    ``factors[s] x`` theta0's; the learner (deploy = "verified", deploy_min_runs = 5)."""
    space, theta0 = lq
    z0, good = _candidate(lq)
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


# deploy = "auto"


def _observe(lr, theta, f1, start):
    y = np.array([f1, 1.0, 0.0, 0.0])
    lr.observe(theta, EpisodeResult(y, np.zeros(len(theta)), True, start_id=start))


def test_auto_resolves_by_the_start_mode(lq):
    space, theta0 = lq
    cyc = make_learner("mobo", space, theta0, seed=0, **FAST)
    assert cyc.deploy_option == "auto" and cyc.deploy == "incumbent"  # nothing seen yet
    for s in range(5):
        _observe(cyc, theta0, BASE[s], s)
    assert (cyc.deploy, cyc.deploy_paired) == ("verified", "cost")
    assert cyc.deploy_rule.model_confidence == 0.5
    assert cyc.deploy_rule.min_runs == CYCLE_UNKNOWN  # the cycle has not wrapped yet
    _observe(cyc, theta0, BASE[0], 0)
    assert (cyc.deploy_rule.min_runs, cyc.deploy_rule.run_cap) == (5, 10)
    assert not cyc.safe_mode  # the default search; only the deployment changes
    rnd = make_learner("mobo", space, theta0, seed=0, **FAST)
    for _ in range(4):
        _observe(rnd, theta0, 1.0, -1)
    # random starts (session 11): the unpaired cost rule (tests/test_deploy_random.py)
    assert (rnd.deploy, rnd.deploy_paired, rnd.deploy_rule.min_runs) == ("verified", "cost", 6)
    assert not rnd.safe_mode


def test_options_set_by_the_user_are_kept(lq):
    space, theta0 = lq
    lr = make_learner("bo", space, theta0, seed=0, deploy="auto", deploy_min_runs=3,
                      deploy_paired="every", **FAST)  # fmt: skip
    for s in (0, 1, 2, 0):
        _observe(lr, theta0, BASE[s], s)
    assert (lr.deploy, lr.deploy_paired, lr.deploy_rule.min_runs) == ("verified", "every", 3)
    assert lr.deploy_rule.model_confidence is None  # 0.5 only with the paired cost test
    fixed = make_learner("bo", space, theta0, seed=0, deploy="incumbent", **FAST)
    for s in (0, 1, 2, 0):
        _observe(fixed, theta0, BASE[s], s)
    assert fixed.deploy == "incumbent"


@pytest.mark.parametrize("factors", [(0.5, 0.5, 1.3, 0.5, 0.5), (0.3, 4.0, 0.3, 0.3, 0.3)])
def test_auto_decides_as_the_explicit_full_cycle_cost_rule(lq, factors):
    """theta0 from the five starts, then a candidate from each: the default learner deploys
    exactly what deploy = "verified", deploy_min_runs = 5, deploy_paired = "cost" deploys
    (the candidate when it is cheaper on average, theta0 when it is dearer on average)."""
    space, theta0 = lq
    z0, good = _candidate(lq)
    cand = space.from_unit(good, base=theta0)
    got = []
    explicit = {"deploy": "verified", "deploy_min_runs": 5, "deploy_paired": "cost",
                "deploy_model_confidence": 0.5}  # fmt: skip
    for opts in ({}, explicit):
        lr = make_learner("bo", space, theta0, seed=0, trust_region="off", **opts, **FAST)
        for s in range(5):
            _observe(lr, theta0, BASE[s], s)
        for s in range(5):
            _observe(lr, cand, BASE[s] * factors[s], s)
        got.append(lr._incumbent_z.copy())
    np.testing.assert_array_equal(got[0], got[1])
    expected = good if np.mean(BASE * np.asarray(factors)) < np.mean(BASE) else z0
    np.testing.assert_allclose(got[0], expected)


def test_auto_resumes_exactly(lq):
    space, theta0 = lq
    a = make_learner("hybrid", space, theta0, seed=2, **FAST)
    rng = np.random.default_rng(3)
    for k in range(9):
        th = a.propose()
        _observe(a, th, float(np.exp(rng.normal() + 0.3 * k % 3)), k % 3)
    state = a.state_dict()
    assert (state["deploy_option"], state["deploy"], state["deploy_paired"]) == (
        "auto", "verified", "cost")  # fmt: skip
    b = make_learner("hybrid", space, theta0, seed=99, **FAST)
    b.load_state_dict(state)
    assert (b.deploy, b.deploy_paired, b.deploy_rule.min_runs) == ("verified", "cost", 3)
    assert b.deploy_rule.model_confidence == a.deploy_rule.model_confidence == 0.5
    np.testing.assert_array_equal(b.incumbent(), a.incumbent())
    np.testing.assert_array_equal(b.propose(), a.propose())


def test_a_checkpoint_from_before_auto_keeps_its_rule(lq):
    """A learner state without "deploy_option" (written before session 10) made with the
    incumbent rule under cycled starts continues with the incumbent rule."""
    space, theta0 = lq
    old = make_learner("bo", space, theta0, seed=0, deploy="incumbent", **FAST)
    for s in (0, 1, 2, 0):
        _observe(old, theta0, BASE[s], s)
    state = {
        k: v for k, v in old.state_dict().items() if k not in ("deploy_option", "deploy_paired")
    }
    new = make_learner("bo", space, theta0, seed=0, **FAST)
    new.load_state_dict(state)
    _observe(new, space.from_unit(space.to_unit(theta0) * 0.95, base=theta0), 0.5, 1)
    assert (new.deploy_option, new.deploy) == ("incumbent", "incumbent")


def test_the_safe_design_keeps_its_own_rule_under_auto(lq):
    """deploy = "auto" (the default) leaves the safe design's deployment rule alone: with
    deploy_confidence set (the safe design) and cycled starts the learner stays on it."""
    space, theta0 = lq
    lr = make_learner("bo", space, theta0, seed=0, deploy_confidence=0.9, **FAST)
    assert lr.safe_mode
    for s in (0, 1, 2, 0):
        _observe(lr, theta0, BASE[s], s)
    assert (lr.deploy, lr.deploy_paired, lr.deploy_rule.min_runs) == ("incumbent", "every", 3)


def test_auto_with_a_single_cycled_start(lq):
    """n_cycle_starts = 1: every episode starts from start 0; the cycle is known after the
    second episode (length 1), and a candidate better than theta0 from that start is deployed
    after one matched episode."""
    space, theta0 = lq
    z0, good = _candidate(lq)
    lr = make_learner("bo", space, theta0, seed=0, trust_region="off", **FAST)
    _observe(lr, theta0, 1.0, 0)
    assert lr.deploy_rule.min_runs == CYCLE_UNKNOWN
    _observe(lr, theta0, 1.01, 0)
    assert lr.deploy_rule.min_runs == 1 and lr._next_start() == 0
    for f in (0.5, 0.52, 0.49):
        _observe(lr, space.from_unit(good, base=theta0), f, 0)
    np.testing.assert_allclose(lr._incumbent_z, good)


@pytest.mark.parametrize("learner", ["bo", "mobo"])
def test_coverage_starts_needs_every_start_of_the_cycle(lq, learner):
    """``deploy_coverage = "starts"`` (session 17, the default since session 18): theta0 from
    the five cycled starts, then a candidate far cheaper from starts 0-2, twice each (six
    matched episodes, ``deploy_min_runs`` = 5 after the wrap), never from starts 3 and 4.
    ``"episodes"`` (the default before) counts episodes and deploys it on that evidence (CSTR
    seed 9 under cycled starts: a theta worse than theta0 on 100 fresh starts, deployed
    without an episode from the start that carries most of theta0's cost); "starts" counts
    three starts, keeps theta0 and verifies the candidate, and deploys it once it has been run
    from the two starts it lacked."""
    space, theta0 = lq
    z0, good = _candidate(lq)
    cand = space.from_unit(good, base=theta0)
    got = {}
    for coverage in ("episodes", None):  # None: the default
        options = {} if coverage is None else {"deploy_coverage": coverage}
        lr = make_learner(learner, space, theta0, seed=0, trust_region="off", **options, **FAST)
        for s in range(5):
            _observe(lr, theta0, BASE[s], s)
        for s in (0, 1, 2, 0, 1, 2):
            _observe(lr, cand, 0.3 * BASE[s], s)
        assert lr.deploy_rule.min_runs == 5
        got[coverage or lr.deploy_coverage] = lr
    np.testing.assert_allclose(got["episodes"]._incumbent_z, good)
    starts = got["starts"]  # KeyError if the default were not "starts"
    assert starts._matched_runs(good) == 3  # distinct starts, short of the cycle
    np.testing.assert_array_equal(starts._incumbent_z, z0)
    np.testing.assert_allclose(starts._verify_z, good)  # run again
    assert starts.state_dict()["deploy_coverage"] == "starts"
    for s in (3, 4):
        _observe(starts, cand, 0.3 * BASE[s], s)
    assert starts._matched_runs(good) == 8  # every start: the episodes count (deploy_max_runs)
    np.testing.assert_allclose(starts._incumbent_z, good)
    old = make_learner(learner, space, theta0, seed=0, deploy_coverage="starts", **FAST)
    old.load_state_dict({k: v for k, v in starts.state_dict().items() if k != "deploy_coverage"})
    assert old.deploy_coverage == "episodes"  # a checkpoint from before keeps its rule
    with pytest.raises(ValueError, match="deploy_coverage.*'episodes', 'starts'"):
        make_learner(learner, space, theta0, deploy_coverage="all")
