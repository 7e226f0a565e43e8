"""The deployment tests of :mod:`mpcmobo.learners.confidence`.

Each function gives the confidence of a one-sided test that a candidate theta is cheaper than
the deployed one from the two thetas' episode costs: the paired t-test of per-start
differences (cycled starts), Welch's test (random starts, no covariate), the analysis of
covariance on each episode's start cost with its leverage guard (random starts), and the
relative screen for a single episode a side. Checked against scipy and an independent
least-squares fit, on the cases they are built for (a hot-spot start, starts that hide a
gain), and on their edge cases: one episode a side, no spread, NaN costs, missing covariates.
The twin's prediction-powered test is checked against the plain tests it reduces to, for its
power with a right twin and its validity with a wrong one.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy import stats

from mpcmobo.learners.confidence import (
    adjusted_confidence,
    ancova_confidence,
    check_confidence,
    paired_confidence,
    relative_screen,
    twin_confidence,
    unpaired_confidence,
)

# ----------------------------------------------------------------------------- paired


@pytest.mark.parametrize("seed", range(4))
def test_paired_confidence_is_scipys_paired_t_test(seed):
    rng = np.random.default_rng(seed)
    base = rng.uniform(1, 3, 4 + seed)
    cand = base * rng.uniform(0.7, 1.2, len(base))
    p = stats.ttest_rel(base, cand, alternative="greater").pvalue
    assert paired_confidence(base - cand) == pytest.approx(1 - p, rel=1e-12, abs=1e-14)


def test_paired_confidence_edge_cases():
    assert paired_confidence(np.array([])) == 0.0
    assert paired_confidence(np.array([0.3])) == 0.5  # one difference: run again, never deploy
    assert paired_confidence(np.array([-0.3])) == 0.0
    assert paired_confidence(np.array([0.0])) == 0.0
    assert paired_confidence(np.array([0.2, 0.2, 0.2])) == 1.0  # no spread: the sign decides
    assert paired_confidence(np.array([-0.2, -0.2])) == 0.0
    d = np.array([0.5, 0.1, 0.3])
    assert paired_confidence(np.r_[d, np.nan]) == paired_confidence(d)  # NaN dropped
    assert paired_confidence(np.array([np.nan, np.nan])) == 0.0


# ----------------------------------------------------------------------------- unpaired


@pytest.mark.parametrize("seed", range(4))
def test_unpaired_confidence_is_scipys_welch_test(seed):
    rng = np.random.default_rng(seed)
    d = np.exp(rng.normal(1.0, 1.0, size=6 + seed))
    c = np.exp(rng.normal(0.5, 0.8, size=4 + 2 * seed))
    ref = stats.ttest_ind(d, c, equal_var=False, alternative="greater").pvalue
    assert unpaired_confidence(d, c) == pytest.approx(1 - ref, rel=1e-9, abs=1e-12)


def test_unpaired_confidence_with_little_evidence():
    assert unpaired_confidence(np.array([2.0, 3.0]), np.array([1.0])) == 0.5  # run again
    assert unpaired_confidence(np.array([2.0]), np.array([3.0, 1.0])) == 0.0  # dearer
    assert unpaired_confidence(np.array([2.0]), np.array([1.0])) == 0.5  # one episode a side
    assert unpaired_confidence(np.array([]), np.array([1.0, 2.0])) == 0.0
    assert unpaired_confidence(np.array([2.0, 2.0]), np.array([1.0, 1.0])) == 1.0  # no spread
    assert unpaired_confidence(np.array([1.0, 1.0]), np.array([2.0, 2.0])) == 0.0
    with_nan = unpaired_confidence(np.array([2.0, np.nan, 3.0]), np.array([1.0, 1.5]))
    assert with_nan == unpaired_confidence(np.array([2.0, 3.0]), np.array([1.0, 1.5])) > 0.9
    assert unpaired_confidence(np.array([2.0, 3.0]), np.array([np.nan, np.inf])) == 0.0


# ----------------------------------------------------------------------------- ANCOVA


def _ancova_by_lstsq(yd, yc, sd, sc):
    """The ANCOVA model y = a + delta [candidate] + b s + e fitted by least squares on the full
    design matrix: the one-sided confidence of delta < 0 from its covariance (n - 3 dof), and
    the diagonal of the hat matrix X (X'X)^-1 X'."""
    y = np.r_[yd, yc]
    g = np.r_[np.zeros(len(yd)), np.ones(len(yc))]
    X = np.column_stack([np.ones(len(y)), g, np.r_[sd, sc]])
    XtX_inv = np.linalg.inv(X.T @ X)
    coef = XtX_inv @ X.T @ y
    r = y - X @ coef
    dof = len(y) - 3
    cov = (r @ r / dof) * XtX_inv
    hat = np.einsum("ij,jk,ik->i", X, XtX_inv, X)
    return stats.t.cdf(-coef[1] / np.sqrt(cov[1, 1]), dof), hat


def _reference(yd, yc, sd, sc):
    """The test on all episodes, the smaller of it and the test without the highest-leverage
    episode, and whether that episode is the candidate's."""
    full, hat = _ancova_by_lstsq(yd, yc, sd, sc)
    i = int(np.argmax(hat))
    if i < len(yd):
        without, _ = _ancova_by_lstsq(np.delete(yd, i), yc, np.delete(sd, i), sc)
    else:
        k = i - len(yd)
        without, _ = _ancova_by_lstsq(yd, np.delete(yc, k), sd, np.delete(sc, k))
    return full, min(full, without), i >= len(yd)


@pytest.mark.parametrize("seed", range(5))
def test_adjusted_confidence_is_the_ancova_t_test(seed):
    rng = np.random.default_rng(seed)
    sd, sc = rng.uniform(1, 10, 6 + seed), rng.uniform(1, 10, 4 + seed)
    yd = 2.0 * sd + rng.normal(0, 1.0, len(sd))
    yc = 2.0 * sc - 0.8 + rng.normal(0, 1.0, len(sc))
    full, ref, _ = _reference(yd, yc, sd, sc)
    assert ancova_confidence(yd, yc, sd, sc) == pytest.approx(full, rel=1e-9, abs=1e-12)
    assert adjusted_confidence(yd, yc, sd, sc) == pytest.approx(ref, rel=1e-9, abs=1e-12)


def test_the_guard_drops_the_candidates_episode_of_highest_leverage():
    """The highest leverage in the candidate's group (a start costlier than all others), the
    only start from which the candidate is clearly cheaper: that episode is left out, as the
    hat matrix says, and the test on the rest does not credit the candidate."""
    sd = np.array([1.0, 2.0, 3.0, 4.0, 2.5])
    sc = np.array([1.5, 2.0, 3.5, 6.0])
    yd = 2.0 * sd + np.array([0.1, -0.2, 0.0, 0.2, -0.1])
    yc = np.array([3.1, 3.9, 7.0, 9.0])  # on the deployed theta's line but at the far start
    full, ref, in_candidate = _reference(yd, yc, sd, sc)
    assert in_candidate
    assert full > 0.7 and ref < 0.5
    assert adjusted_confidence(yd, yc, sd, sc) == pytest.approx(ref, rel=1e-9)


def test_the_guard_falls_back_to_welch_where_the_rest_has_no_test():
    """Two episodes of the deployed theta (equal leverage, the highest): without one of them
    the test is undefined (one episode a side), so the guard takes Welch's test on the rest,
    which gives a single episode no more than 0.5, whatever the test on all episodes says."""
    sd, sc = np.array([1.0, 9.0]), np.array([2.0, 3.0, 4.0, 5.0])
    yd, yc = np.array([3.0, 8.5]), np.array([1.5, 2.0, 3.2, 3.9])
    full, hat = _ancova_by_lstsq(yd, yc, sd, sc)
    assert hat[:2].min() > hat[2:].max()
    assert full > 0.99
    assert unpaired_confidence(yd[:1], yc) == unpaired_confidence(yd[1:], yc) == 0.5
    assert adjusted_confidence(yd, yc, sd, sc) == 0.5


def test_no_decision_rests_on_one_episode():
    """CSTR episodes under random starts, theta0 against a design point after six episodes
    each: one hot-spot start of theta0 (cost 979347, covariate 13428) sets the slope, and the
    candidate, which never met such a start, looks better on all episodes (above 0.9); it is
    1.6 times worse than theta0 on 100 fresh starts. Without that episode it is not credited."""
    yd = np.array([1866.0, 979347.0, 41568.0, 14863.0, 2373.0, 7899.0])
    sd = np.array([3092.0, 13428.0, 3349.0, 3043.0, 2900.0, 2406.0])
    yc = np.array([1752.0, 36937.0, 2027.0, 954.0, 86879.0, 1023.0])
    sc = np.array([4012.0, 2615.0, 4272.0, 3095.0, 6304.0, 2313.0])
    assert ancova_confidence(yd, yc, sd, sc) > 0.9
    assert adjusted_confidence(yd, yc, sd, sc) < 0.7
    assert adjusted_confidence(yd, yc, sd, sc) == pytest.approx(_reference(yd, yc, sd, sc)[1])


@settings(max_examples=40, deadline=None)
@given(
    scale=st.floats(1e-3, 1e3),
    shift=st.floats(-1e3, 1e3),
    seed=st.integers(0, 2**16),
)
def test_the_covariates_units_do_not_matter(scale, shift, seed):
    rng = np.random.default_rng(seed)
    sd, sc = rng.uniform(1, 5, 6), rng.uniform(1, 5, 6)
    yd, yc = sd + rng.normal(0, 0.3, 6), sc - 0.2 + rng.normal(0, 0.3, 6)
    a = adjusted_confidence(yd, yc, sd, sc)
    b = adjusted_confidence(yd, yc, scale * sd + shift, scale * sc + shift)
    assert b == pytest.approx(a, abs=1e-6)


def test_it_sees_a_gain_the_starts_hide_from_welch():
    """Costs proportional to how costly the start is, the candidate 10% cheaper from every
    start, its starts happening to be costlier: Welch sees a dearer candidate, the adjusted
    test (also without any one episode) a cheaper one."""
    rng = np.random.default_rng(0)
    sd = rng.uniform(1, 3, 6)
    sc = rng.uniform(2, 4, 6)
    yd = sd * (1 + 0.01 * rng.normal(size=6))
    yc = 0.9 * sc * (1 + 0.01 * rng.normal(size=6))
    assert unpaired_confidence(yd, yc) < 0.1
    assert adjusted_confidence(yd, yc, sd, sc) > 0.99
    # and a candidate 10% dearer from every start with easier starts is refused
    assert unpaired_confidence(sc, 1.1 * sd) > 0.9
    assert adjusted_confidence(sc, 1.1 * sd, sc, sd) < 0.01


def test_an_exact_fit_is_decided_by_the_sign():
    s_d, s_c = np.array([1.0, 2.0, 4.0]), np.array([1.5, 3.0, 5.0])
    assert adjusted_confidence(2 * s_d, 2 * s_c - 1, s_d, s_c) == pytest.approx(1.0, abs=1e-9)
    assert adjusted_confidence(2 * s_d, 2 * s_c + 1, s_d, s_c) == pytest.approx(0.0, abs=1e-9)


def test_ancova_is_undefined_without_two_episodes_a_side_or_a_covariate():
    y, s = np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, 3.0])
    assert ancova_confidence(y, y[:1], s, s[:1]) is None
    assert ancova_confidence(y[:1], y, s[:1], s) is None
    assert ancova_confidence(y, y, s, np.r_[s[:2], np.nan]) is None
    assert ancova_confidence(y, y, np.ones(3), np.ones(3)) is None  # no spread within groups


def test_adjusted_confidence_falls_back_to_welch():
    yd, yc = np.array([2.0, 3.0, 4.0]), np.array([1.0, 1.5, 2.5])
    welch = unpaired_confidence(yd, yc)
    nan = np.full(3, np.nan)
    assert adjusted_confidence(yd, yc, nan, nan) == welch  # no covariate
    s = np.array([1.0, 2.0, 3.0])
    assert adjusted_confidence(yd, yc, s, np.r_[1.0, np.nan, 2.0]) == welch  # one missing
    assert adjusted_confidence(yd, yc, np.ones(3), np.ones(3)) == welch  # no spread
    one = adjusted_confidence(yd[:1], yc[:1], s[:1], s[:1])  # one episode a side
    assert one == unpaired_confidence(yd[:1], yc[:1]) == 0.5
    assert adjusted_confidence(yd, yc[:1], yd, yc[:1]) == unpaired_confidence(yd, yc[:1])
    # a failed episode (inf, NaN) is dropped with its covariate
    with_inf = adjusted_confidence(np.r_[yd, np.inf], np.r_[yc, np.nan], np.r_[s, 5.0], np.r_[s, 9])
    assert with_inf == adjusted_confidence(yd, yc, s, s)
    assert adjusted_confidence(yd, np.full(2, np.nan), s, s[:2]) == 0.0  # nothing left


# ----------------------------------------------------------------------------- the screen

# `lq` under random starts: theta0's two episodes from costly starts, and a candidate's three
# from cheap ones, each 3-8% cheaper relative to its start (on 100 fresh starts this candidate
# is 5% cheaper than theta0 in f1)
Y0, S0 = np.array([0.552, 0.466]), np.array([0.765, 0.649])
S1 = np.array([0.096, 0.126, 0.100])
Y1 = np.array([0.695, 0.673, 0.662]) * S1


def test_the_screen_is_the_ratio_of_means():
    s = np.array([1.0, 2.0, 4.0])
    assert relative_screen(s, 0.95 * s, s, s) == 0.5
    assert relative_screen(s, 1.05 * s, s, s) == 0.0
    assert relative_screen(s, s, s, s) == 0.0  # equal: not better
    # the ratio of means, not the mean of the ratios: a start near the equilibrium (s tiny,
    # its ratio large) does not carry the candidate's mean
    yc, sc = np.array([0.05, 1.6, 3.2]), np.array([0.01, 2.0, 4.0])
    assert np.mean(yc / sc) > 1.0 and yc.sum() / sc.sum() < 1.0
    assert relative_screen(s, yc, s, sc) == 0.5
    # without a positive covariate on every episode: the raw means
    nan = np.full(3, np.nan)
    assert relative_screen(s, 0.5 * s, nan, nan) == 0.5
    assert relative_screen(s, 2.0 * s, s, np.zeros(3)) == 0.0
    assert relative_screen(s, 1.1 * s, s, 0.5 * np.r_[s[:2], np.nan]) == 0.0  # raw: dearer
    # a failed episode (inf) is dropped with its covariate; nothing left: not better
    assert relative_screen(np.r_[s, np.inf], 0.95 * s, np.r_[s, 1.0], s) == 0.5
    assert relative_screen(s, np.array([np.nan]), s, np.ones(1)) == 0.0
    assert relative_screen(np.array([]), s, np.array([]), s) == 0.0


def test_the_screen_at_one_episode_a_side_reads_the_start():
    """One episode each, the candidate's from a costly start: dearer raw (Welch: 0), cheaper
    relative to its start (the screen: 0.5)."""
    yd, sd, yc, sc = np.array([0.072]), np.array([0.1]), np.array([0.56]), np.array([0.8])
    assert unpaired_confidence(yd, yc) == 0.0
    assert adjusted_confidence(yd, yc, sd, sc) == 0.0
    assert relative_screen(yd, yc, sd, sc) == 0.5


def test_the_test_on_few_episodes_drops_a_candidate_the_screen_keeps():
    """On these five episodes the adjusted test is below 0.5 (a candidate judged worse is
    neither deployed nor run again); the screen keeps it."""
    assert adjusted_confidence(Y0, Y1, S0, S1) < 0.5
    assert relative_screen(Y0, Y1, S0, S1) == 0.5


# ----------------------------------------------------------------------------- the option


def test_check_confidence_names_the_option():
    assert check_confidence("deploy.confidence", 0.5) == 0.5
    assert check_confidence("deploy.confidence", 0.95) == 0.95
    for bad in (0.49, 1.0, 1.5):
        with pytest.raises(ValueError, match=r"deploy\.confidence must be in \[0.5, 1\)"):
            check_confidence("deploy.confidence", bad)


# ----------------------------------------------------------------------------- the twin's test


def _hot_starts(rng, n):
    """How costly ``n`` starts are: heavy-tailed, as the CSTR's (a few carry the mean)."""
    return rng.lognormal(0.0, 1.0, n)


def test_a_right_twin_lends_its_simulated_starts():
    """A twin that predicts the plant's episodes exactly (ratio 1 on every start): the test is
    the paired t-test on its 64 simulated starts, whatever six plant starts say."""
    rng = np.random.default_rng(0)
    h = _hot_starts(rng, 70)
    J_d, J_c = h, 0.85 * h * (1 + rng.normal(0, 0.3, 70))  # the candidate: 15% cheaper
    plant = slice(0, 6)
    d_side = (J_d[plant], J_d[plant].copy(), J_d[6:])
    c_side = (J_c[plant], J_c[plant].copy(), J_c[6:])
    conf = twin_confidence(d_side, c_side, paired=True)
    assert conf == pytest.approx(paired_confidence(J_d[6:] - J_c[6:]), abs=1e-12)
    assert paired_confidence(J_d[plant] - J_c[plant]) < 0.9 < conf


def _trial(rng, gain, factor, n=6, M=64, narrow=False):
    """One decision: ``n`` plant starts (cool ones if ``narrow``), ``M`` simulated ones, the
    candidate ``gain`` cheaper on average, exploration noise on the plant's costs, and a twin
    that sees the candidate's costs ``factor`` times lower than they are."""
    h = rng.lognormal(-0.5, 0.2, n) if narrow else _hot_starts(rng, n)
    hs = _hot_starts(rng, M)

    def cand(x):
        return x * (1 - gain) * (1 + rng.normal(0, 0.3, len(x)))

    jc, jcs = cand(h), cand(hs)
    noisy = lambda j: j * (1 + rng.normal(0, 0.1, len(j)))  # noqa: E731
    return (noisy(h), h, hs), (noisy(jc), jc * factor, jcs * factor)


@pytest.mark.parametrize("narrow", [False, True])
def test_a_wrong_twin_costs_power_not_validity(narrow):
    """A candidate no better in truth, a twin that sees it 30% cheaper than it is: the plant's
    episodes correct the twin, and at confidence 0.9 the candidate is deployed in about 10% of
    trials, also when the plant's starts are a cool corner of the distribution (a cycle) --
    where PPI's difference rectifier, which cannot see the twin's error on hot starts, deploys
    it in most. The twin's simulated starts alone would deploy it almost always."""
    rng = np.random.default_rng(3)
    trials = [_trial(rng, 0.0, 0.7, narrow=narrow) for _ in range(1500)]
    rate = np.mean([twin_confidence(d, c, paired=True) >= 0.9 for d, c in trials])
    twin_alone = np.mean([paired_confidence(d[2] - c[2]) >= 0.9 for d, c in trials])
    assert 0.05 < rate < 0.14
    assert twin_alone > 0.99


def test_a_right_twin_doubles_the_power():
    """A candidate 10% cheaper and a right twin: deployed about twice as often as by the
    paired test on the same six plant starts."""
    rng = np.random.default_rng(4)
    trials = [_trial(rng, 0.1, 1.0) for _ in range(1500)]
    rate = np.mean([twin_confidence(d, c, paired=True) >= 0.9 for d, c in trials])
    plain = np.mean([paired_confidence(d[0] - c[0]) >= 0.9 for d, c in trials])
    assert rate > 1.6 * plain


def test_the_unpaired_twin_test_reads_each_sides_own_starts():
    """Random starts: the candidate's episodes come from costly starts, the deployed theta's
    from cheap ones; Welch's test finds the candidate dearer, the twin, right on every start,
    finds it 10% cheaper."""
    rng = np.random.default_rng(5)
    hs = _hot_starts(rng, 64)
    cheap, costly = np.array([0.3, 0.4, 0.5, 0.6]), np.array([2.0, 3.0, 2.5, 4.0])
    d_side = (cheap, cheap.copy(), hs)
    c_side = (0.9 * costly, 0.9 * costly, 0.9 * hs)
    assert unpaired_confidence(cheap, 0.9 * costly) < 0.01
    assert twin_confidence(d_side, c_side, paired=False) > 0.99


def test_the_twins_test_edge_cases():
    y = np.array([1.0, 2.0, 3.0])
    sim = np.linspace(0.5, 4.0, 64)
    d, c = (y, y, sim), (0.5 * y, 0.5 * y, 0.5 * sim)
    assert twin_confidence(d, c, paired=True) > 1 - 1e-12  # half the cost on every start
    assert twin_confidence(c, d, paired=True) < 1e-12
    flat = (y, y, np.full(64, 2.0)), (0.5 * y, 0.5 * y, np.full(64, 1.0))
    assert twin_confidence(*flat, paired=True) == 1.0  # no spread at all: the sign decides
    # fewer than two usable plant starts or simulated ones, or predictions that are not
    # positive: the plain test
    one = (y[:1], y[:1], sim), (0.5 * y[:1], 0.5 * y[:1], 0.5 * sim)
    assert twin_confidence(*one, paired=True) == paired_confidence(0.5 * y[:1]) == 0.5
    nan_sim = (y, y, np.array([1.0, np.nan])), (0.5 * y, 0.5 * y, np.array([0.5, np.nan]))
    assert twin_confidence(*nan_sim, paired=True) == paired_confidence(0.5 * y)
    neg = (y, -y, sim), (0.5 * y, 0.5 * y, 0.5 * sim)
    assert twin_confidence(*neg, paired=False) == unpaired_confidence(y, 0.5 * y)
    # a failed prediction drops its start from both sides (paired)
    yn = np.r_[y, 9.0]
    with_nan = (yn, np.r_[y, np.nan], sim), (0.5 * yn, 0.5 * yn, 0.5 * sim)
    d2 = (y + np.array([0.1, -0.1, 0.05]), y, sim)
    assert twin_confidence(*with_nan, paired=True) == twin_confidence(d, c, paired=True)
    assert 0.5 < twin_confidence(d2, c, paired=True) <= 1.0
