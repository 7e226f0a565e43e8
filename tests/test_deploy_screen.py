"""Screening candidates relative to their starts below ``deploy_min_runs`` (issue 11, session 14).

Under random starts a GP learner's candidate is run again, alternating with the deployed theta,
until each has ``deploy_min_runs`` episodes; the start-adjusted test
(:func:`~mpcmobo.learners.deploy.adjusted_confidence`) then decides. With ``deploy_screen =
"relative"`` (opt-in) the candidate is only screened before that point
(:func:`~mpcmobo.learners.deploy.relative_screen`): kept while its cost relative to its starts is
below the deployed theta's. The test itself (``"test"``) on two or three episodes drops good
candidates for good: its intercept extrapolates between starts that do not overlap, and a
dropped candidate is never run again. The default since session 17, ``"first"``, screens
relatively only at one episode a side, where the test has no degrees of freedom.
"""

from __future__ import annotations

import numpy as np
import pytest

from mpcmobo.learners import EpisodeResult, make_learner
from mpcmobo.learners.deploy import adjusted_confidence, relative_screen
from mpcmobo.systems import get_system

FAST = {"n_init": 3, "num_restarts": 2, "raw_samples": 32, "maxiter": 20, "trust_region": "off"}

# session 14, `lq` bo seed 1 (random starts): theta0's two episodes from larger starts, and a
# candidate's three from small ones, each 3-8% cheaper relative to its start (on 100 fresh
# starts this candidate is 5% cheaper than theta0 in f1)
Y0, S0 = np.array([0.552, 0.466]), np.array([0.765, 0.649])
S1 = np.array([0.096, 0.126, 0.100])
Y1 = np.array([0.695, 0.673, 0.662]) * S1


def test_the_screen_is_the_ratio_of_means():
    s = np.array([1.0, 2.0, 4.0])
    assert relative_screen(s, 0.95 * s, s, s) == 0.5
    assert relative_screen(s, 1.05 * s, s, s) == 0.0
    # the ratio of means, not the mean of the ratios: a start near the equilibrium (s tiny,
    # its ratio large) does not carry the candidate's mean
    yc, sc = np.array([0.05, 1.6, 3.2]), np.array([0.01, 2.0, 4.0])
    assert np.mean(yc / sc) > 1.0 and yc.sum() / sc.sum() < 1.0
    assert relative_screen(s, yc, s, sc) == 0.5
    # without a positive covariate on every episode: the raw means
    nan = np.full(3, np.nan)
    assert relative_screen(s, 0.5 * s, nan, nan) == 0.5
    assert relative_screen(s, 2.0 * s, s, np.zeros(3)) == 0.0
    # a failed episode (inf) is dropped with its covariate; nothing left: not better
    assert relative_screen(np.r_[s, np.inf], 0.95 * s, np.r_[s, 1.0], s) == 0.5
    assert relative_screen(s, np.array([np.nan]), s, np.ones(1)) == 0.0


def test_the_test_on_few_episodes_dropped_the_lq_candidate():
    """The case of session 14: the adjusted test on these five episodes is below 0.5 (a
    candidate judged worse is neither deployed nor run again); the screen keeps it."""
    assert adjusted_confidence(Y0, Y1, S0, S1) < 0.5
    assert relative_screen(Y0, Y1, S0, S1) == 0.5


def _observe(lr, theta, f1, s):
    y = np.array([f1, 1.0, 0.0, 0.0])
    lr.observe(theta, EpisodeResult(y, np.zeros(len(theta)), True, start_id=-1, start_cost=s))


@pytest.mark.parametrize("learner", ["bo", "mobo"])
def test_gp_learners_verify_a_screened_candidate(learner):
    """A bo / mobo learner with ``deploy_screen = "relative"`` and those episodes keeps
    verifying the candidate (the next verification; the deployed theta is kept); the default
    ("first", with two episodes a side here) and a checkpoint from before session 14 judge it
    by the test on few episodes, and drop it."""
    lq = get_system("lq")
    space, theta0 = lq.search_space, lq.parameterization.theta0
    z0 = space.to_unit(theta0)
    cand = z0.copy()
    cand[1] += 0.05
    lr = make_learner(learner, space, theta0, seed=0, deploy_screen="relative", **FAST)
    for f, s in zip(Y0, S0, strict=True):
        _observe(lr, theta0, f, s)
    for f, s in zip(Y1, S1, strict=True):
        _observe(lr, space.from_unit(cand, base=theta0), f, s)
    assert lr._paired_cost(cand, z0) == 0.5
    np.testing.assert_array_equal(lr._incumbent_z, z0)
    assert lr._verify_z is not None
    np.testing.assert_allclose(lr._verify_z, cand)
    kind, z = lr._verification()  # the deployed theta has fewer episodes: its turn
    assert kind == "baseline"
    np.testing.assert_array_equal(z, z0)

    state = lr.state_dict()
    assert state["deploy_screen"] == "relative"
    again = make_learner(learner, space, theta0, seed=0, **FAST)
    again.load_state_dict(state)  # the checkpoint's rule wins, as deploy_adjust's
    assert again._paired_cost(cand, z0) == 0.5
    old = make_learner(learner, space, theta0, seed=0, deploy_screen="relative", **FAST)
    old.load_state_dict({k: v for k, v in state.items() if k != "deploy_screen"})
    test = pytest.approx(adjusted_confidence(Y0, Y1, S0, S1))
    assert old.deploy_screen == "test" and old._paired_cost(cand, z0) == test

    default = make_learner(learner, space, theta0, seed=0, **FAST)
    for f, s in zip(Y0, S0, strict=True):
        _observe(default, theta0, f, s)
    for f, s in zip(Y1, S1, strict=True):
        _observe(default, space.from_unit(cand, base=theta0), f, s)
    assert default._paired_cost(cand, z0) == test
    assert default._verify_z is None or not np.allclose(default._verify_z, cand)


@pytest.mark.parametrize("learner", ["bo", "mobo"])
def test_first_screens_only_single_episodes(learner):
    """``deploy_screen = "first"`` (session 16, the default since session 17): session 15's
    `lq` trace, theta0's only episode from a cheap start and a candidate's first from a costly
    one, cheaper relative to it. ``"test"`` (the default before) falls back to the raw costs
    there (0: the candidate is dropped and never run again); "first" screens it on the
    relative cost (0.5: run again). From two episodes a side it is the test, like "test"."""
    lq = get_system("lq")
    space, theta0 = lq.search_space, lq.parameterization.theta0
    z0 = space.to_unit(theta0)
    cand = z0.copy()
    cand[1] += 0.05
    theta_c = space.from_unit(cand, base=theta0)
    first = make_learner(learner, space, theta0, seed=0, **FAST)  # the default
    before = make_learner(learner, space, theta0, seed=0, deploy_screen="test", **FAST)
    for lr in (first, before):
        _observe(lr, theta0, 0.72 * 0.1, 0.1)
        _observe(lr, theta_c, 0.70 * 0.8, 0.8)
    assert before._paired_cost(cand, z0) == 0.0
    assert first._paired_cost(cand, z0) == 0.5
    np.testing.assert_allclose(first._verify_z, cand)
    assert first._verification()[0] == "verify"  # then theta0, alternating (baseline)
    for lr in (first, before):
        _observe(lr, theta0, 0.72 * 0.5, 0.5)
        _observe(lr, theta_c, 0.71 * 0.2, 0.2)
    test = adjusted_confidence([0.072, 0.36], [0.56, 0.142], [0.1, 0.5], [0.8, 0.2])
    assert first._paired_cost(cand, z0) == pytest.approx(test)
    assert before._paired_cost(cand, z0) == pytest.approx(test)
    assert first.state_dict()["deploy_screen"] == "first"


def _run_with_theta0_best(lr, space, theta0, episodes):
    """Random starts on a cost proportional to the start, lowest at theta0."""
    z0 = space.to_unit(theta0)
    rng = np.random.default_rng(0)
    for _ in range(episodes):
        theta = lr.propose()
        s = float(rng.uniform(0.1, 1.0))
        _observe(lr, theta, 0.72 * s * (1.0 + np.sum((space.to_unit(theta) - z0) ** 2)), s)
    return lr


def test_early_baseline_runs_the_deployed_theta_between_searches():
    """``deploy_baseline = "early"`` (session 16, the default since session 17): after the
    initial design the deployed theta is run again, alternating with the search, until it has
    ``deploy_min_runs`` (6 under random starts) episodes, then the search goes on alone;
    ``"verify"`` (the default before) runs it only to match a verified candidate (none here:
    theta0 is the cheapest)."""
    lq = get_system("lq")
    space, theta0 = lq.search_space, lq.parameterization.theta0
    early = make_learner("bo", space, theta0, seed=0, **FAST)  # the default
    _run_with_theta0_best(early, space, theta0, 16)
    kinds = early.proposal_kinds_
    assert kinds[:3] == ["design"] * 3
    assert kinds[3:13] == ["baseline", "search"] * 5  # theta0: 1 design + 5 baseline episodes
    assert kinds[13:] == ["search"] * 3
    assert early._runs(space.to_unit(theta0)) == 6
    assert early.state_dict()["deploy_baseline"] == "early"

    verify = make_learner("bo", space, theta0, seed=0, deploy_baseline="verify", **FAST)
    _run_with_theta0_best(verify, space, theta0, 16)
    assert "baseline" not in verify.proposal_kinds_
    with pytest.raises(ValueError, match="deploy_baseline.*'verify', 'early'"):
        make_learner("bo", space, theta0, deploy_baseline="always")


def test_bad_deploy_screen_names_the_option():
    lq = get_system("lq")
    with pytest.raises(ValueError, match="deploy_screen.*'test', 'relative'"):
        make_learner("bo", lq.search_space, lq.parameterization.theta0, deploy_screen="ratio")
