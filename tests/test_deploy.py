"""The deployment policies of the GP learners (:mod:`mpcmobo.learners.deploy`).

A candidate theta replaces the deployed one only on the evidence of its own episodes against
the deployed theta's: under cycled starts (:class:`CycledEvidence`) once it has been run from
every start of the cycle and is cheaper from the same starts on the mean cost (paired); under
random starts (:class:`RandomEvidence`) on the start-adjusted test with ``min_runs`` episodes a
side, screened relative to its start while a side has one episode, the deployed theta run
again early. The incumbent rule deploys the GP's best observed point.

Through the learners (``make_learner(..., starts=...)``) fed crafted episodes on the `lq`
system's search space, and through the policies' own ``decide``, ``next_check``, ``runs`` and
``confidence_of`` on evidence built by hand where that says more; the twin's judgement
(``verdict`` once a twin judges). Last, the covariate the evidence policies read, each
episode's start cost, as the learning loop computes it.
"""

from __future__ import annotations

import pickle
import warnings

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mpcmobo.bo import GPSurrogate
from mpcmobo.learners import EpisodeResult, Learner, Replay, Starts, make_learner
from mpcmobo.learners.confidence import (
    adjusted_confidence,
    paired_confidence,
    relative_screen,
    unpaired_confidence,
)
from mpcmobo.learners.deploy import (
    CycledEvidence,
    Decision,
    Incumbent,
    RandomEvidence,
    make_policy,
)
from mpcmobo.learners.evidence import Evidence, theta_key
from mpcmobo.learners.options import EvidenceDeploy, IncumbentDeploy
from mpcmobo.learners.registry import LearnerOptionError
from mpcmobo.learners.twin import Twin
from mpcmobo.systems import get_system

FAST = {"n_init": 3, "search": {"num_restarts": 2, "raw_samples": 32, "maxiter": 20}}
BASE = np.exp([0.0, 1.0, -1.0, 0.5, -0.5])  # theta0's cost from each of 5 cycled starts


@pytest.fixture(autouse=True)
def _quiet_botorch():
    """BoTorch warns that f2..f4 (constant here) are not standardised."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Data .* is not standardized")
        yield


@pytest.fixture(scope="module")
def lq():
    s = get_system("lq")
    return s.search_space, s.parameterization.theta0


def _points(lq):
    """theta0's unit point and a candidate 0.1 away from it in the first coordinate."""
    space, theta0 = lq
    z0 = space.to_unit(theta0)
    good = z0.copy()
    good[0] += 0.1
    return z0, good


def _observe(lr, z, f1, start=-1, start_cost=float("nan")):
    y = np.array([f1, 1.0, 0.0, 0.0])
    res = EpisodeResult(y, np.zeros(lr.space.n_theta), True, start_id=start, start_cost=start_cost)
    lr.observe(lr.theta_of(z), res)


def _same(a, b) -> bool:
    return a is not None and b is not None and theta_key(a) == theta_key(b)


# ============================================================================ cycled starts


def _cycle(lq, factors, name="bo"):
    """theta0 from the five cycled starts, then the candidate from each with cost
    ``factors[s]`` times theta0's (no trust region)."""
    z0, good = _points(lq)
    lr = make_learner(
        name, lq[0], lq[1], seed=0, starts=Starts("cycle", 5), trust_region=False, **FAST
    )
    assert isinstance(lr.policy, CycledEvidence)
    for s in range(5):
        _observe(lr, z0, BASE[s], s)
    for s in range(5):
        _observe(lr, good, BASE[s] * factors[s], s)
    return lr, z0, good


def test_a_little_dearer_from_one_start_is_deployed_on_the_mean_cost(lq):
    """Half the cost from four starts, 30% dearer from the cheapest one: the paired test on
    the episode costs (what J averages) is confident, and the candidate is deployed."""
    factors = np.array([0.5, 0.5, 1.3, 0.5, 0.5])
    lr, z0, good = _cycle(lq, factors)
    ev = lr.evidence_
    assert lr.policy.runs(ev, good, z0) == 5
    conf = lr.policy.confidence_of(ev, lr.surrogate, good, z0)
    assert conf == pytest.approx(paired_confidence(BASE * (1 - factors)))
    assert conf >= 0.9
    assert _same(lr.deployed_z_, good) and lr.verify_z_ is None
    np.testing.assert_allclose(lr.incumbent(), lr.theta_of(good))


@pytest.mark.parametrize("name", ["bo", "mobo"])
def test_a_simulated_episode_teaches_the_gp_but_is_no_evidence(lq, name):
    """The same candidate as above, half the cost from every start, but simulated (the
    exploration budget refused it): the GP fits it, the evidence has no run of it, and it is
    neither deployed nor verified; once the plant runs it the same way, it is deployed."""
    z0, good = _points(lq)
    lr = make_learner(
        name, lq[0], lq[1], seed=0, starts=Starts("cycle", 5), trust_region=False, **FAST
    )
    assert lr.learns_in_simulation()
    for s in range(5):
        _observe(lr, z0, BASE[s], s)
    for s in range(5):
        y = np.array([0.5 * BASE[s], 1.0, 0.0, 0.0])
        res = EpisodeResult(y, np.zeros(lr.space.n_theta), True, start_id=s)
        lr.observe_simulated(lr.theta_of(good), res)
    ev = lr.evidence_
    assert len(ev) == 10 and ev.kinds[5:] == ["simulated"] * 5
    assert lr.policy.runs(ev, good, z0) == 0 and len(ev.rows_of(good)) == 0
    assert _same(lr.deployed_z_, z0) and lr.verify_z_ is None
    mean, _ = lr.surrogate.to_cost_space(*lr.surrogate.posterior_model_space(good[None, :]))
    mean0, _ = lr.surrogate.to_cost_space(*lr.surrogate.posterior_model_space(z0[None, :]))
    assert mean[0, 0] < mean0[0, 0]  # the GP has learned it is cheaper
    for s in range(5):
        _observe(lr, good, 0.5 * BASE[s], s)
    assert _same(lr.deployed_z_, good)


def test_the_incumbent_rule_deploys_only_a_theta_the_plant_ran(lq):
    """The paper's rule picks the GP's best observed theta among the plant's episodes: a
    cheaper simulated one is not deployed."""
    z0, good = _points(lq)
    lr = make_learner("bo", lq[0], lq[1], seed=0, deploy=IncumbentDeploy(), **FAST)
    for _ in range(3):
        _observe(lr, z0, 1.0)
    y = np.array([0.1, 1.0, 0.0, 0.0])
    lr.observe_simulated(lr.theta_of(good), EpisodeResult(y, np.zeros(lr.space.n_theta), True))
    assert _same(lr.deployed_z_, z0)


def test_cheaper_in_log_cost_but_dearer_on_average_is_refused(lq):
    """0.3 of theta0's cost from four starts, 4 times from the dearest: cheaper in the mean of
    the log costs, dearer in the mean cost: refused and not run again."""
    factors = np.array([0.3, 4.0, 0.3, 0.3, 0.3])
    assert np.mean(np.log(factors)) < 0 < np.mean(BASE * (factors - 1))
    lr, z0, good = _cycle(lq, factors)
    assert lr.policy.confidence_of(lr.evidence_, lr.surrogate, good, z0) < 0.5
    assert _same(lr.deployed_z_, z0) and lr.verify_z_ is None
    np.testing.assert_array_equal(lr.incumbent(), lq[1])  # theta0 itself


def test_unmatched_episodes_are_no_evidence(lq):
    """theta0 run from start 0 only, the candidate (half the cost) from starts 1-4: none of
    its episodes has a match, so it has no runs and is not deployed."""
    z0, good = _points(lq)
    lr = make_learner(
        "bo", lq[0], lq[1], seed=0, starts=Starts("cycle", 5), trust_region=False, **FAST
    )
    _observe(lr, z0, 1.0, 0)
    for s in range(1, 5):
        _observe(lr, good, 0.5 * BASE[s], s)
    assert lr.policy.runs(lr.evidence_, good, z0) == 0
    assert _same(lr.deployed_z_, z0)


def test_verification_runs_from_the_next_start_or_the_deployed_theta_first(lq):
    """Four cycled starts, the trust region on. theta0 from starts 0 and 1 (the design), a
    worse point (a failure of the trust region), then a cheaper candidate from start 1: it is
    verified from start 2 next, which the deployed theta lacks, so theta0 runs there first
    (and from 3), then the candidate from 0, 1, 2 and 3. Verification and baseline episodes are
    neither successes nor failures; the candidate, once run from every start, is deployed, a
    success."""
    space, theta0 = lq
    z0, good = _points(lq)
    bad = z0.copy()
    bad[0] -= 0.1
    options = {**FAST, "n_init": 2}
    lr = make_learner("bo", space, theta0, seed=0, starts=Starts("cycle", 4), **options)
    off = np.array([0.0, 0.3, -0.3, 0.15])

    def cost(z, s):
        return float(np.exp(off[s] - 2.0 * (z[0] - z0[0])))

    for s in (0, 1):
        _observe(lr, z0, cost(z0, s), s)
    _observe(lr, bad, cost(bad, 0), 0)
    assert lr.trust_.failures == 1 and lr.verify_z_ is None and lr.verifying() is None
    _observe(lr, good, cost(good, 1), 1)
    assert _same(lr.verify_z_, good) and _same(lr.deployed_z_, z0)
    np.testing.assert_array_equal(lr.verifying(), lr.theta_of(good))  # what status names
    assert lr.trust_.failures == 1  # it earned a verification: not a failure
    for s in (2, 3):  # start 2 (then 3) next: the deployed theta has no episode there
        kind, z = lr.policy.next_check(lr.evidence_, lr.deployed_z_, lr.verify_z_)
        assert kind == "baseline" and _same(z, z0)
        theta = lr.propose()
        np.testing.assert_array_equal(theta, theta0)  # theta0 itself, not its round trip
        _observe(lr, z0, cost(z0, s), s)
        assert lr.evidence_.kinds[-1] == "baseline"
        assert lr.trust_.failures == 1
    for s in (0, 1, 2, 3):  # the cycle goes on: the candidate from every start
        assert _same(lr.deployed_z_, z0)  # not before it has every start
        np.testing.assert_allclose(space.to_unit(lr.propose()), good)
        assert lr.pending_[0] == "verify"
        _observe(lr, good, cost(good, s), s)
        assert lr.evidence_.kinds[-1] == "verify"
        assert lr.trust_.failures == 1 or _same(lr.deployed_z_, good)
    assert lr.evidence_.starts_of(good) == {0, 1, 2, 3}
    assert lr.policy.runs(lr.evidence_, good, z0) == 5  # every start: the matched episodes
    assert _same(lr.deployed_z_, good) and lr.verify_z_ is None
    assert (lr.trust_.successes, lr.trust_.failures) == (1, 0)


def _evidence(rows, dim=1):
    """An Evidence of one objective from rows ``(z, f1, start, start_cost)``."""
    ev = Evidence(dim, 1, 1)
    for z, f, s, c in rows:
        ev.append(np.atleast_1d(np.asarray(z, float)), [f], [0.0], s, c, "search")
    return ev


A, B = np.array([0.2]), np.array([0.8])  # the deployed theta and a candidate (1-D)


def test_cycled_runs_count_distinct_matched_starts_until_the_whole_cycle():
    """Six episodes of the candidate from three of five starts count as three; once it has
    every start, its matched episodes count (eight); episodes from a start the deployed theta
    lacks never count."""
    policy = CycledEvidence(n_starts=5, confidence=0.9, kappa=1.0)
    rows = [(A, BASE[s], s, np.nan) for s in range(4)]  # the deployed theta lacks start 4
    rows += [(B, 0.3 * BASE[s], s, np.nan) for s in (0, 1, 2, 0, 1, 2)]
    assert policy.runs(_evidence(rows), B, A) == 3
    rows += [(B, 0.3 * BASE[s], s, np.nan) for s in (3, 4)]
    assert policy.runs(_evidence(rows), B, A) == 4  # start 4 unmatched
    rows += [(A, BASE[4], 4, np.nan)]
    assert policy.runs(_evidence(rows), B, A) == 8
    assert policy.runs(_evidence(rows + [(B, np.nan, 3, np.nan)]), B, A) == 8  # failed: none


def test_cycled_confidence_pairs_each_episode_with_the_deployed_mean_from_its_start():
    policy = CycledEvidence(n_starts=3, confidence=0.9, kappa=1.0)
    rows = [(A, 1.0, 0, np.nan), (A, 3.0, 0, np.nan), (A, 4.0, 1, np.nan)]  # start 0: mean 2
    rows += [(B, 1.5, 0, np.nan), (B, 3.0, 1, np.nan), (B, 9.0, 2, np.nan)]  # start 2: no match
    ev = _evidence(rows)
    assert policy.confidence_of(ev, None, B, A) == paired_confidence(np.array([0.5, 1.0]))
    rows[4] = (B, 4.5, 1, np.nan)
    assert policy.confidence_of(_evidence(rows), None, B, A) == pytest.approx(
        paired_confidence(np.array([0.5, -0.5]))
    )


def test_cycled_confidence_without_a_matched_start_asks_the_gp():
    """No start in common: the candidate's episodes are compared with the GP's prediction of
    the deployed theta, cheaper (confident) or dearer (not)."""
    policy = CycledEvidence(n_starts=4, confidence=0.9, kappa=1.0)
    rows = [(A, 1.0 + 0.02 * k, k % 2, np.nan) for k in range(4)]
    ev = _evidence(rows)
    sur = GPSurrogate(1, log_outcomes=[True], group_outputs=[True]).fit(
        ev.Z, ev.Y, groups=ev.starts
    )
    cheap = _evidence(rows + [(B, 0.3, 2, np.nan), (B, 0.31, 3, np.nan)])
    dear = _evidence(rows + [(B, 3.0, 2, np.nan), (B, 3.1, 3, np.nan)])
    assert policy.confidence_of(cheap, sur, B, A) > 0.9
    assert policy.confidence_of(dear, sur, B, A) < 0.05
    assert policy.confidence_of(_evidence(rows), sur, B, A) == 0.0  # no episode at all


def test_cycled_next_check():
    policy = CycledEvidence(n_starts=3, confidence=0.9, kappa=1.0)
    rows = [(A, 1.0, 0, np.nan), (A, 1.0, 1, np.nan), (B, 0.5, 0, np.nan)]
    assert policy.next_check(_evidence(rows), A, None) is None  # nothing to verify
    kind, z = policy.next_check(_evidence(rows), A, B)  # next: start 1, which A has
    assert kind == "verify" and _same(z, B)
    kind, z = policy.next_check(_evidence(rows + [(B, 0.5, 1, np.nan)]), A, B)  # next: 2
    assert kind == "baseline" and _same(z, A)
    rows += [(B, 0.5, 1, np.nan), (A, 1.0, 2, np.nan)]
    assert policy.next_check(_evidence(rows), A, B)[0] == "verify"  # next: 0, wrapped


# ============================================================================ random starts


def _random(lq, name="bo", **options):
    lr = make_learner(
        name, lq[0], lq[1], seed=0, starts=Starts("random"), trust_region=False, **FAST, **options
    )
    assert isinstance(lr.policy, RandomEvidence) and lr.uses_start_cost()
    return lr


def test_one_episode_a_side_is_screened_relative_to_the_start_then_tested(lq):
    """theta0's episode from a cheap start, the candidate's first from a costly one, cheaper
    relative to it: the screen keeps it (0.5, where the raw costs say 0) and it runs again;
    from two episodes a side the adjusted test judges it, not the screen."""
    z0, cand = _points(lq)
    lr = _random(lq)
    _observe(lr, z0, 0.72 * 0.1, start_cost=0.1)
    _observe(lr, cand, 0.70 * 0.8, start_cost=0.8)
    ev = lr.evidence_
    assert unpaired_confidence(ev.Y[:1, 0], ev.Y[1:, 0]) == 0.0
    assert lr.policy.confidence_of(ev, lr.surrogate, cand, z0) == 0.5
    assert _same(lr.verify_z_, cand) and _same(lr.deployed_z_, z0)
    kind, z = lr.policy.next_check(ev, lr.deployed_z_, lr.verify_z_)
    assert kind == "verify" and _same(z, cand)
    _observe(lr, z0, 0.72 * 0.3, start_cost=0.3)
    _observe(lr, cand, 0.69 * 0.6, start_cost=0.6)
    ev = lr.evidence_
    y, s = ev.Y[:, 0], ev.start_costs
    assert relative_screen(y[[0, 2]], y[[1, 3]], s[[0, 2]], s[[1, 3]]) == 0.5
    test = adjusted_confidence(y[[0, 2]], y[[1, 3]], s[[0, 2]], s[[1, 3]])
    assert test == 0.0  # the test, not the screen
    assert lr.policy.confidence_of(ev, lr.surrogate, cand, z0) == test


S0 = np.array([1.0, 3.0, 0.5, 2.0, 8.0, 1.5])  # start costs of theta0's six random starts
S1 = np.array([4.0, 6.0, 3.0, 9.0, 5.0, 7.0, 5.0, 8.0, 3.5, 6.5, 4.5, 7.5])  # the candidate's


@pytest.mark.parametrize("name", ["bo", "mobo"])
def test_the_start_adjusted_test_deploys_a_gain_the_starts_hide(lq, name):
    """theta0's costs are its start costs, the candidate's 0.8 of theirs from costlier starts:
    dearer raw (Welch), cheaper from every start; deployed on the adjusted test once it has
    ``2 min_runs`` episodes (no twin), not at ``min_runs``. The GP sees f1 relative to the
    start cost, the evidence keeps f1 itself."""
    z0, good = _points(lq)
    lr = _random(lq, name)
    noise = 1 + 0.01 * np.random.default_rng(0).normal(size=18)
    for f, s in zip(S0 * noise[:6], S0):
        _observe(lr, z0, f, start_cost=s)
    for k, (f, s) in enumerate(zip(0.8 * S1 * noise[6:], S1)):
        assert not _same(lr.deployed_z_, good), k
        _observe(lr, good, f, start_cost=s)
    ev = lr.evidence_
    f1 = np.r_[S0 * noise[:6], 0.8 * S1 * noise[6:]]
    np.testing.assert_array_equal(ev.Y[:, 0], f1)
    np.testing.assert_allclose(lr._model_Y()[:, 0], f1 / np.r_[S0, S1])
    np.testing.assert_allclose(lr.surrogate.train_Y[:, 0], f1 / np.r_[S0, S1])
    assert unpaired_confidence(ev.Y[:6, 0], ev.Y[6:, 0]) < 0.5
    conf = lr.policy.confidence_of(ev, lr.surrogate, good, z0)
    assert conf == pytest.approx(adjusted_confidence(ev.Y[:6, 0], ev.Y[6:, 0], S0, S1))
    assert conf > 0.99
    assert _same(lr.deployed_z_, good)


THETA0 = np.array([1.0, 3.0, 0.5, 2.0, 8.0, 1.5])  # theta0's costs from six random starts


def test_cheaper_typically_but_dearer_on_average_is_refused(lq):
    """No covariate (the tests fall back to Welch's): five of six episodes below theta0's
    median, one heavy tail that makes the mean dearer: refused and not run again."""
    z0, good = _points(lq)
    cand = np.array([0.3, 0.9, 0.2, 0.6, 0.4, 30.0])
    assert np.median(cand) < np.median(THETA0) and cand.mean() > THETA0.mean()
    lr = _random(lq)
    for f in THETA0:
        _observe(lr, z0, f)
    for f in cand:
        _observe(lr, good, f)
    assert lr.policy.confidence_of(lr.evidence_, lr.surrogate, good, z0) < 0.5
    assert _same(lr.deployed_z_, z0) and lr.verify_z_ is None


def test_the_deployed_theta_runs_early_alternating_with_the_search(lq):
    """After the design the deployed theta is run again, alternating with the search, until
    it has ``min_runs`` episodes (3 here), then the search goes on alone (theta0 is the
    cheapest relative to its start, so no candidate is verified)."""
    space, theta0 = lq
    z0 = space.to_unit(theta0)
    lr = _random(lq, deploy={"min_runs": 3})
    assert lr.policy.min_runs == 3
    rng = np.random.default_rng(0)
    for _ in range(9):
        theta = lr.propose()
        s = float(rng.uniform(0.1, 1.0))
        z = space.to_unit(theta)
        f = 0.72 * s * (1.0 + np.sum((z - z0) ** 2))
        lr.observe(
            theta, EpisodeResult(np.array([f, 1.0, 0.0, 0.0]), np.zeros(9), True, start_cost=s)
        )
    assert lr.evidence_.kinds == ["design"] * 3 + ["baseline", "search"] * 2 + ["search"] * 2
    assert lr.evidence_.runs(z0) == 3
    assert lr.verify_z_ is None


def test_the_gp_models_f1_relative_to_the_start_under_random_starts_only(lq):
    """``_model_Y``: f1 / start cost under the random-start evidence policy (a row without a
    usable start cost takes the others' median), f1 itself under cycled starts (start offsets
    instead) and under the incumbent rule."""
    space, theta0 = lq
    z0 = space.to_unit(theta0)
    costs = np.array([1.0, 2.0, 4.0, np.nan, 0.0])
    f1 = np.array([2.0, 4.0, 8.0, 6.0, 5.0])
    learners = {
        "random": _random(lq),
        "cycle": make_learner("bo", space, theta0, starts=Starts("cycle", 3), **FAST),
        "incumbent": make_learner("bo", space, theta0, deploy="incumbent", **FAST),
    }
    for mode, lr in learners.items():
        for k, (f, s) in enumerate(zip(f1, costs)):
            start = k % 3 if mode == "cycle" else -1
            lr.evidence_.append(z0, [f], np.zeros(9), start, s, "design")
    Y = learners["random"]._model_Y()
    np.testing.assert_allclose(Y[:, 0], f1 / np.array([1.0, 2.0, 4.0, 2.0, 2.0]))
    np.testing.assert_array_equal(learners["random"].evidence_.Y[:, 0], f1)  # kept as is
    for mode in ("cycle", "incumbent"):
        np.testing.assert_array_equal(learners[mode]._model_Y(), learners[mode].evidence_.Y)
    assert not learners["incumbent"].uses_start_cost()


def test_random_next_check():
    """A candidate to verify waits for the deployed theta to have as many episodes (up to
    ``2 min_runs``); without one, the deployed theta runs again after every search episode
    until it has ``min_runs``."""
    policy = RandomEvidence(confidence=0.9, min_runs=2, kappa=1.0)
    a = [(A, 1.0, -1, 1.0)]
    b = [(B, 0.5, -1, 1.0)]
    kind, z = policy.next_check(_evidence(a + 2 * b), A, B)
    assert kind == "baseline" and _same(z, A)
    kind, z = policy.next_check(_evidence(2 * a + 2 * b), A, B)
    assert kind == "verify" and _same(z, B)
    assert policy.next_check(_evidence(4 * a + 6 * b), A, B)[0] == "verify"  # capped at 4
    ev = _evidence(a + b)  # the last episode a search point's: the deployed theta's turn
    assert policy.next_check(ev, A, None)[0] == "baseline"
    ev.kinds[-1] = "baseline"
    assert policy.next_check(ev, A, None) is None  # the search's turn
    assert policy.next_check(_evidence(2 * a + b), A, None) is None  # it has min_runs


# ---------------------------------------------------------------------- decide, by hand


@pytest.fixture(scope="module")
def slope():
    """GPs on a 1-D cost rising from z = 0 to 1 (LO cheaper than HI) and on one falling."""
    rng = np.random.default_rng(0)
    X = rng.uniform(size=(12, 1))
    noise = 0.02 * rng.normal(size=12)
    rising = GPSurrogate(1, log_outcomes=[True]).fit(X, np.exp(0.5 * X[:, 0] + noise)[:, None])
    falling = GPSurrogate(1, log_outcomes=[True]).fit(X, np.exp(-0.5 * X[:, 0] + noise)[:, None])
    return rising, falling


LO, HI = np.array([0.1]), np.array([0.9])  # the GP on a rising cost prefers LO


def _decide(sur, deployed_costs, candidate_costs, min_runs=3, confidence=0.9):
    """RandomEvidence's decision with HI deployed and LO the candidate (no covariate)."""
    policy = RandomEvidence(confidence=confidence, min_runs=min_runs, kappa=0.0)
    rows = [(HI, f, -1, np.nan) for f in deployed_costs]
    rows += [(LO, f, -1, np.nan) for f in candidate_costs]
    ev = _evidence(rows)
    return policy.decide(ev, sur, HI.copy(), seed=0), policy.confidence_of(ev, sur, LO, HI)


DEPLOYED = np.array([2.0, 2.4, 1.8])


def test_decide_verifies_until_the_candidate_has_min_runs(slope):
    d, conf = _decide(slope[0], DEPLOYED, [0.5, 0.6])
    assert conf > 0.99
    assert isinstance(d, Decision) and _same(d.deployed, HI) and _same(d.verify, LO)


CHEAP = np.array([0.5, 0.6, 0.55, 0.52, 0.58, 0.57])  # the candidate's, 2 min_runs of them


def test_decide_deploys_on_evidence_once_both_sides_have_enough(slope):
    """Without a twin the candidate needs ``2 min_runs`` episodes, the deployed theta
    ``min_runs``."""
    d, conf = _decide(slope[0], DEPLOYED, CHEAP[:3])
    assert conf > 0.99 and _same(d.deployed, HI) and _same(d.verify, LO)  # min_runs: not yet
    d, _ = _decide(slope[0], DEPLOYED, CHEAP)
    assert _same(d.deployed, LO) and d.verify is None
    d, _ = _decide(slope[0], DEPLOYED[:2], CHEAP)  # the deployed theta has two
    assert _same(d.deployed, HI) and _same(d.verify, LO)


def test_without_a_twin_the_candidate_is_judged_once_on_twice_min_runs(slope):
    """Three lucky episodes, convincing at ``min_runs``, then three no cheaper than the
    deployed theta's: run again at three, judged once at six and dropped. Once a twin judges,
    ``min_runs`` episodes are enough."""
    cand = np.array([0.2, 0.25, 0.22, 2.6, 2.5, 2.7])
    d, conf = _decide(slope[0], DEPLOYED, cand[:3])
    assert conf > 0.99 and _same(d.deployed, HI) and _same(d.verify, LO)
    d, conf = _decide(slope[0], DEPLOYED, cand)
    assert 0.5 <= conf < 0.9 and _same(d.deployed, HI) and d.verify is None
    policy = RandomEvidence(confidence=0.9, min_runs=3, kappa=0.0)
    assert policy.needed() == 6
    policy.twin = _twin()
    assert policy.needed() == 3


def test_decide_runs_a_promising_candidate_again_up_to_twice_min_runs(slope):
    cand = np.array([1.9, 2.2, 1.7, 2.3, 1.8, 2.1])
    for n, again in ((3, True), (5, True), (6, False)):
        d, conf = _decide(slope[0], DEPLOYED, cand[:n])
        assert 0.5 <= conf < 0.9, conf  # promising, not convincing
        assert _same(d.deployed, HI)
        assert _same(d.verify, LO) if again else d.verify is None


def test_decide_drops_a_candidate_the_evidence_rules_out(slope):
    d, conf = _decide(slope[0], DEPLOYED, [2.5, 2.9, 2.6])
    assert conf < 0.5
    assert _same(d.deployed, HI) and d.verify is None


def test_decide_needs_the_gp_to_prefer_the_candidate(slope):
    """Convincing episodes, but the GP finds the deployed theta cheaper: kept."""
    d, conf = _decide(slope[1], DEPLOYED, [0.5, 0.6, 0.55])
    assert conf > 0.99
    assert _same(d.deployed, HI) and d.verify is None


# ============================================================================ judged by a twin


def _twin_cost(starts, theta, params, noise=None):
    """A model's closed-loop cost of a 1-D theta from each start (n, 1): a start of size
    exp(x); the candidate (theta 0.8) saves 20% of it where x > -0.5 and costs 30% more where
    x <= -0.5. ``params`` scales the model's costs of the candidate (1: the plant's)."""
    x = np.asarray(starts, float)[:, 0]
    size = np.exp(x)
    gain = np.where(x > -0.5, 0.2, -0.3) * float(theta[0] > 0.5) * float(params[0])
    return size * (1.0 - gain)


def _twin(params=1.0):
    rng = np.random.default_rng(0)
    starts = rng.uniform(-1.0, 1.0, size=(64, 1))  # three quarters where the candidate saves
    return Twin(np.array([params]), _twin_cost, starts)


def _plant_evidence(n_starts, x0s, noise=0.0):
    """Each theta once from each cycled start, its plant cost the model's (params 1) times
    ``1 + noise`` drawn per episode; every row with its cost and initial state."""
    rng = np.random.default_rng(1)
    ev = Evidence(1, 1, 1)
    for z in (A, B):
        for s in range(n_starts):
            c = float(_twin_cost(x0s[s][None, :], z, [1.0])[0]) * (1 + noise * rng.normal())
            ev.append(z, [c], [0.0], s, np.nan, "verify", cost=c, replay=Replay(x0s[s]))
    return ev


def test_the_evidence_keeps_each_episodes_replay_through_a_checkpoint():
    """A replay (initial state and exploration) survives the evidence's state as plain arrays;
    an unknown one stays unknown; an initial state alone (a 1.0 state) is a noise-free replay;
    a twin refuses an initial state of the wrong size, naming it."""
    ev = Evidence(1, 1, 1)
    kept = Replay(np.array([0.3]), np.arange(6.0).reshape(3, 2))
    ev.append(A, [1.0], [0.0], 0, np.nan, "verify", cost=1.0, replay=kept)
    ev.append(B, [2.0], [0.0], 1, np.nan, "verify", cost=2.0)
    state = pickle.loads(pickle.dumps(ev.state_dict()))
    assert all(isinstance(r, dict | type(None)) for r in state["replays"])
    back = Evidence(1, 1, 1)
    back.load_state_dict(state)
    assert back.replays[1] is None
    assert back.replays[0] is not None and back.replays[0].exploration is not None
    np.testing.assert_array_equal(back.replays[0].x0, kept.x0)
    np.testing.assert_array_equal(back.replays[0].exploration, kept.exploration)
    old = Replay.from_state(np.array([0.3]))
    assert old is not None and old.exploration is None
    assert Replay.from_state(np.zeros(0)) is None
    with pytest.raises(ValueError, match=r"initial state has shape \(2,\)"):
        _twin().predict(A, [Replay(np.array([0.1, 0.2]))])


def test_a_twin_deploys_what_the_population_gains_though_the_cycle_loses():
    """The cycle's three starts are where the candidate loses (x <= -0.5): the paired test
    refuses it; the twin, right at those starts, shows the gain on its 64 simulated starts
    and deploys it."""
    policy = CycledEvidence(n_starts=3, confidence=0.9, kappa=1.0)
    x0s = [np.array([-0.9]), np.array([-0.7]), np.array([-0.6])]
    ev = _plant_evidence(3, x0s, noise=0.02)
    assert policy.verdict(ev, None, B, A) == policy.confidence_of(ev, None, B, A) < 0.05
    policy.twin = _twin()
    assert policy.verdict(ev, None, B, A) > 0.99


def test_a_twin_the_plant_contradicts_does_not_deploy():
    """A twin that overstates the candidate's gain and loss twofold (params 2) where the plant
    has the candidate 5% dearer everywhere: the plant's episodes show the twin's predictions of
    the candidate 55% too low, that correction reaches the simulated starts, and the candidate
    is not deployed."""
    policy = CycledEvidence(n_starts=4, confidence=0.9, kappa=1.0)
    x0s = [np.array([x]) for x in (-0.9, 0.1, 0.4, 0.8)]
    ev = Evidence(1, 1, 1)
    for z, factor in ((A, 1.0), (B, 1.05)):  # the plant: the candidate 5% dearer everywhere
        for s, x0 in enumerate(x0s):
            c = float(np.exp(x0[0])) * factor
            ev.append(z, [c], [0.0], s, np.nan, "verify", cost=c, replay=Replay(x0))
    policy.twin = _twin(params=2.0)
    twin_alone = policy.twin.simulate(A) - policy.twin.simulate(B)
    assert paired_confidence(twin_alone) > 0.99  # the twin alone would deploy
    assert policy.verdict(ev, None, B, A) < 0.5


def test_a_twin_judges_random_starts_by_each_thetas_episodes():
    """Random starts: each theta's episodes with the twin's predictions of them; the
    candidate's come from costly starts, the deployed theta's from cheap ones: dearer raw, cheaper
    by the twin."""
    policy = RandomEvidence(confidence=0.9, min_runs=3, kappa=0.0)
    ev = Evidence(1, 1, 1)
    for z, xs in ((A, (-0.9, -0.8, -0.6)), (B, (0.6, 0.8, 0.9))):
        for x in xs:
            x0 = np.array([x])
            c = float(_twin_cost(x0[None, :], z, [1.0])[0])
            ev.append(z, [c], [0.0], -1, np.nan, "verify", cost=c, replay=Replay(x0))
    assert policy.verdict(ev, None, B, A) < 0.5
    policy.twin = _twin()
    assert policy.verdict(ev, None, B, A) > 0.99


# ============================================================================ the incumbent


def test_the_incumbent_rule_deploys_the_gps_risk_averse_best():
    """Ten noisy episodes of one theta against one lucky episode elsewhere: with kappa = 0
    the lowest predicted f1 (the lucky point), with kappa = 3 the well-supported point."""
    rng = np.random.default_rng(0)
    a, b = np.full(8, 0.3), np.full(8, 0.9)
    rows = [(a, f, -1, np.nan) for f in 1000 * np.exp(0.5 * rng.normal(size=10))]
    ev = _evidence(rows + [(b, 700.0, -1, np.nan)], dim=8)
    sur = GPSurrogate(1, log_outcomes=[True]).fit(ev.Z, ev.Y)
    assert _same(Incumbent(0.0).decide(ev, sur, a, seed=0).deployed, b)
    assert _same(Incumbent(3.0).decide(ev, sur, a, seed=0).deployed, a)
    assert Incumbent(0.0).next_check(ev, a, None) is None


def test_the_incumbent_rule_deploys_without_evidence(lq):
    """``deploy = "incumbent"``: one cheaper episode is enough; nothing is run again."""
    z0, good = _points(lq)
    lr = make_learner(
        "bo", lq[0], lq[1], deploy="incumbent", incumbent_kappa=0.0, trust_region=False, **FAST
    )
    assert isinstance(lr.policy, Incumbent) and not lr.policy.gathers_evidence
    _observe(lr, z0, 1.0)
    _observe(lr, z0, 1.1)
    _observe(lr, good, 0.3)
    assert _same(lr.deployed_z_, good) and lr.verify_z_ is None


# ============================================================================ options


def test_the_policy_is_chosen_by_the_start_design_and_the_option(lq):
    space, theta0 = lq
    cyc = make_policy(EvidenceDeploy(confidence=0.95), Starts("cycle", 4), kappa=2.0)
    assert isinstance(cyc, CycledEvidence)
    assert (cyc.min_runs, cyc.max_runs, cyc.confidence, cyc.kappa) == (4, 8, 0.95, 2.0)
    rnd = make_policy(EvidenceDeploy(min_runs=5), Starts("random"), kappa=1.0)
    assert isinstance(rnd, RandomEvidence) and rnd.relative
    assert (rnd.min_runs, rnd.max_runs, rnd.confidence) == (5, 10, 0.9)
    assert isinstance(make_policy(IncumbentDeploy(), Starts("cycle", 3), 1.0), Incumbent)
    for name in ("bo", "mobo", "hybrid"):
        lr = make_learner(name, space, theta0, starts=Starts("cycle", 6))
        assert isinstance(lr.policy, CycledEvidence) and lr.policy.min_runs == 6
        assert isinstance(make_learner(name, space, theta0).policy, RandomEvidence)
        lr = make_learner(name, space, theta0, deploy={"rule": "incumbent"})
        assert isinstance(lr.policy, Incumbent)
    lr = make_learner("bo", space, theta0, deploy={"confidence": 0.8, "min_runs": 4})
    assert (lr.policy.confidence, lr.policy.min_runs) == (0.8, 4)
    assert lr.options.deploy == EvidenceDeploy(confidence=0.8, min_runs=4)


@pytest.mark.parametrize(
    "deploy, match",
    [
        ({"confidence": 1.0}, r"deploy\.confidence: .*less than 1"),
        ({"confidence": 0.4}, r"deploy\.confidence: .*greater than or equal to 0.5"),
        ({"min_runs": 1}, r"deploy\.min_runs: "),
        ({"rule": "incumbent", "confidence": 0.9}, r"deploy\.confidence: unknown option"),
        ({"runs": 6}, r"deploy\.runs: unknown option"),
        ("verified", r"deploy: .*'evidence', 'incumbent'"),
    ],
)
def test_bad_deploy_options_name_the_option(lq, deploy, match):
    with pytest.raises(LearnerOptionError, match=match) as err:
        make_learner("bo", lq[0], lq[1], deploy=deploy)
    assert "the options of 'bo'" in str(err.value)
    assert isinstance(err.value, ValueError)


@pytest.mark.parametrize("removed", ["deploy_min_runs", "deploy_paired", "deploy_screen"])
def test_removed_deploy_options_are_unknown(lq, removed):
    with pytest.raises(LearnerOptionError, match=rf"^{removed}: unknown option"):
        make_learner("mobo", lq[0], lq[1], **{removed: 3})


def test_bad_start_designs_are_refused():
    with pytest.raises(ValueError, match="start mode must be 'cycle' or 'random'"):
        Starts("ring")
    with pytest.raises(ValueError, match="n_starts must be at least 1"):
        Starts("cycle", 0)


# ============================================================================ the covariate


@pytest.fixture(scope="module")
def lq_system():
    return get_system("lq")


def test_the_loop_gives_the_start_cost_of_theta0_on_the_model(lq_system):
    """EpisodeResult.start_cost is theta0's mean stage cost from the episode's start in a
    closed loop on the MPC's own model: checked against a loop written here with the model's
    equations (System.model_step) and the MPC's inputs; computed once per start; NaN for a
    learner that does not ask for it."""
    from mpcmobo.experiment.loop import LearningRun
    from mpcmobo.mpc import ParametricMPC

    mpc = ParametricMPC(lq_system)
    theta0 = lq_system.parameterization.theta0

    class Asks(Learner):
        name = "asks"

        def __init__(self, asks):
            super().__init__(lq_system.search_space, theta0)
            self.asks, self.results = asks, []

        def propose(self):
            return theta0.copy()

        def uses_start_cost(self):
            return self.asks

        def observe(self, theta, result):
            self.results.append(result)

        def incumbent(self):
            return theta0.copy()

    learner = Asks(True)
    run = LearningRun(
        lq_system,
        learner,
        mpc,
        seed=1,
        steps=8,
        exploration_std=[0.3],
        start_mode="cycle",
        n_cycle_starts=2,
    )
    for _ in range(3):
        run.run_episode()
    assert len(run._start_costs) == 2  # the third episode reuses the first start's value
    x = run.cycle_starts[0].copy()
    mpc.reset()
    costs = []
    for _ in range(8):
        u = lq_system.clip_input(mpc.solve(x, theta0, sensitivities=False).action)
        costs.append(lq_system.stage_cost(x, u))
        x = lq_system.model_step(x, u)
    ref = float(np.mean(costs))
    assert learner.results[0].start_cost == pytest.approx(ref, rel=1e-8)
    assert learner.results[2].start_cost == learner.results[0].start_cost
    plant = learner.results[0].stage_cost
    assert np.isfinite(plant) and plant != pytest.approx(
        ref, rel=1e-3
    )  # the model is not the plant

    quiet = Asks(False)
    LearningRun(lq_system, quiet, mpc, seed=1, steps=8, start_mode="cycle").run_episode()
    assert np.isnan(quiet.results[0].start_cost)


def test_a_failing_covariate_never_ends_a_run(lq_system, monkeypatch):
    """The start cost of a learner is that of its theta0; a closed loop
    on the model that fails gives NaN (the tests then fall back to Welch), and the episode is
    recorded as usual."""
    import mpcmobo.experiment.loop as loop
    from mpcmobo.mpc import ParametricMPC

    mpc = ParametricMPC(lq_system)

    class Bare(Learner):  # theta0: the system's
        name = "bare"

        def __init__(self):
            super().__init__(lq_system.search_space, lq_system.parameterization.theta0)
            self.results = []

        def propose(self):
            return lq_system.parameterization.theta0.copy()

        def uses_start_cost(self):
            return True

        def observe(self, theta, result):
            self.results.append(result)

        def incumbent(self):
            return lq_system.parameterization.theta0.copy()

    bare = Bare()
    run = loop.LearningRun(
        lq_system, bare, mpc, seed=2, steps=5, start_mode="cycle", n_cycle_starts=1
    )
    run.run_episode()
    assert np.isfinite(bare.results[0].start_cost)

    def broken(*args, **kwargs):
        raise TypeError("no model")

    monkeypatch.setattr(loop, "model_rollout", broken)
    other = Bare()
    run = loop.LearningRun(
        lq_system, other, mpc, seed=2, steps=5, start_mode="cycle", n_cycle_starts=1
    )
    row, _ = run.run_episode()
    assert np.isnan(other.results[0].start_cost) and np.isnan(row["start_cost"])
    assert row["error"] == "" and np.isfinite(row["f1"])
    assert other.results[0].f1 == bare.results[0].f1  # the same episode as with a covariate


def test_a_candidate_with_a_failed_episode_is_never_deployed(lq):
    """Half theta0's cost from every start of the cycle, but one episode of it failed (a plant
    that diverged: a cost that is not finite): never the candidate, never deployed."""
    z0, good = _points(lq)
    lr = make_learner(
        "bo", lq[0], lq[1], seed=0, starts=Starts("cycle", 5), trust_region=False, **FAST
    )
    for s in range(5):
        _observe(lr, z0, BASE[s], s)
    _observe(lr, good, float("nan"), 0)
    for s in range(5):
        _observe(lr, good, 0.5 * BASE[s], s)
    assert theta_key(good) in lr.evidence_.failed()
    assert lr.policy.confidence_of(lr.evidence_, lr.surrogate, good, z0) >= 0.9
    assert _same(lr.deployed_z_, z0) and lr.verify_z_ is None


@settings(max_examples=60, deadline=None)
@given(
    st.lists(st.integers(0, 5), min_size=1, max_size=30),
    st.sampled_from([0.0, -0.0, -1e-12, 1e-10, 0.3, 1.0]),
)
def test_the_rows_of_a_theta_are_those_of_its_key(picks, special):
    """``Evidence.rows_of(z)``: the finite plant rows whose :func:`theta_key` is ``z``'s, row
    by row (a NaN row and a simulated row are not evidence; -0.0 and 0.0 are two keys, as the
    keys' bytes are)."""
    pool = np.random.default_rng(len(picks)).random((6, 3))
    pool[1, 0], pool[2] = special, pool[3] + 1e-11  # within the key's rounding of row 3
    ev = Evidence(3, 3, 1)
    for i, k in enumerate(picks):
        y = [np.nan] if i % 7 == 6 else [1.0]
        ev.append(pool[k], y, np.zeros(3), 0, 1.0, "simulated" if i % 5 == 4 else "design")
    for z in [*pool, np.array([0.0, *pool[1, 1:]]), np.array([-0.0, *pool[1, 1:]])]:
        expected = [
            i
            for i, zz in enumerate(ev.Z)
            if np.isfinite(ev.Y[i, 0])
            and ev.kinds[i] != "simulated"
            and theta_key(zz) == theta_key(z)
        ]
        assert ev.rows_of(z).tolist() == expected
