"""Tests of mpcmobo.bo: Pareto tools, GP surrogate, EI and EHVI proposals (small n, fast)."""

from __future__ import annotations

import pickle

import numpy as np
import pytest
import torch
from botorch.models import SingleTaskGP
from botorch.models.transforms.outcome import Standardize
from botorch.utils.sampling import draw_sobol_samples

from mpcmobo.bo import (
    AcqfSearch,
    EHVIOptions,
    GPSurrogate,
    hypervolume,
    pareto_mask,
    propose_ehvi,
    propose_ei,
    reference_point,
)
from mpcmobo.bo.fastpost import ExactIndependentGP
from mpcmobo.bo.transforms import cost_transform


def sobol(n: int, d: int, seed: int) -> np.ndarray:
    b = torch.stack([torch.zeros(d), torch.ones(d)]).double()
    return draw_sobol_samples(b, n=n, q=1, seed=seed).squeeze(1).numpy()


# ----------------------------------------------------------------------------- pareto
def test_pareto_mask_hand_computed():
    Y = np.array(
        [
            [1.0, 4.0],  # front
            [2.0, 2.0],  # front
            [4.0, 1.0],  # front
            [3.0, 3.0],  # dominated by (2, 2)
            [2.0, 2.0],  # duplicate of a front point: kept
            [np.nan, 0.0],  # non-finite: never Pareto
            [4.0, 1.5],  # weakly dominated by (4, 1)
        ]
    )
    np.testing.assert_array_equal(pareto_mask(Y), [True, True, True, False, True, False, False])


def _non_dominated_by_definition(Y: np.ndarray) -> np.ndarray:
    """Row i is kept iff it is finite and no finite row j has Y_j <= Y_i everywhere and
    Y_j < Y_i somewhere (the O(n^2 m) definition)."""
    ok = np.all(np.isfinite(Y), axis=1)
    F = Y[ok]
    le = np.all(F[None, :, :] <= F[:, None, :], axis=2)
    lt = np.any(F[None, :, :] < F[:, None, :], axis=2)
    mask = np.zeros(len(Y), dtype=bool)
    mask[ok] = ~np.any(le & lt, axis=1)
    return mask


@pytest.mark.parametrize("m", [1, 2, 3, 4, 5])
def test_pareto_mask_matches_the_definition_with_ties_duplicates_and_nan(m):
    rng = np.random.default_rng(m)
    for n in (0, 1, 7, 300):
        Y = rng.integers(0, 4, size=(n, m)).astype(float)  # many ties and exact duplicates
        Y = np.vstack([Y, rng.normal(size=(n, m)), Y[: n // 3]])
        Y[rng.random(Y.shape) < 0.03] = np.nan
        Y[rng.random(Y.shape) < 0.01] = -np.inf
        np.testing.assert_array_equal(pareto_mask(Y), _non_dominated_by_definition(Y))


def test_hypervolume_hand_computed():
    ref = np.array([5.0, 5.0])
    # single point: (5-1)*(5-2)
    assert hypervolume(np.array([[1.0, 2.0]]), ref) == pytest.approx(12.0)
    # staircase (1,4),(2,2),(4,1) w.r.t. (5,5): 4*1 + 3*2 + 1*... computed by slabs in f1:
    # [1,2): height 5-4=1; [2,4): 5-2=3; [4,5): 5-1=4  -> 1 + 6 + 4 = 11
    Y = np.array([[1.0, 4.0], [2.0, 2.0], [4.0, 1.0], [3.0, 3.0]])
    assert hypervolume(Y, ref) == pytest.approx(11.0)
    # points not dominating ref and NaN rows contribute nothing
    Y2 = np.vstack([Y, [[6.0, 0.0], [0.0, 5.0], [np.nan, np.nan]]])
    assert hypervolume(Y2, ref) == pytest.approx(11.0)
    assert hypervolume(np.empty((0, 2)), ref) == 0.0
    # 3-D box
    assert hypervolume(np.array([[0.0, 0.0, 0.0]]), np.array([1.0, 2.0, 3.0])) == pytest.approx(6)


def test_reference_point_rule():
    Y = np.array([[1.0, 10.0], [3.0, 20.0], [2.0, np.nan]])
    r = reference_point(Y, margin=0.1)
    # nadir of the finite rows (3, 20) + 0.1 * range (2, 10)
    np.testing.assert_allclose(r, [3.2, 21.0])
    # fixed rule: does not depend on later (better or worse) observations unless recomputed
    assert np.all(r > np.nanmax(Y[:2], axis=0))
    # zero range: margin relative to |max|
    np.testing.assert_allclose(reference_point(np.array([[2.0], [2.0]]), 0.5), [3.0])


# ----------------------------------------------------------------------------- surrogate
def test_a_constant_output_is_modelled_as_that_constant_without_a_warning():
    """f3 is 0 over a run's first episodes: the GP predicts 0 for it, and BoTorch's warning
    that the output is not standardised stays out of the run's log; other warnings do not."""
    import warnings

    from botorch.exceptions.warnings import InputDataWarning

    X = sobol(6, 2, seed=0)
    Y = np.column_stack([X.sum(1), np.zeros(6)])
    with warnings.catch_warnings():
        warnings.simplefilter("error", InputDataWarning)
        sur = GPSurrogate(2).fit(X, Y)
    mean, _ = sur.predict(sobol(4, 2, seed=1))
    np.testing.assert_allclose(mean[:, 1], 0.0, atol=1e-9)
    with pytest.warns(InputDataWarning, match="not standardized"):  # without the filter
        SingleTaskGP(torch.as_tensor(X), torch.as_tensor(Y), outcome_transform=Standardize(m=2))


def test_surrogate_drops_nan_rows_and_predicts():
    X = sobol(12, 2, seed=0)
    Y = np.column_stack([np.sin(6 * X[:, 0]) + X[:, 1], (X**2).sum(1)])
    Y[3, 0] = np.nan
    Y[7, 1] = np.inf
    sur = GPSurrogate(2).fit(X, Y)
    assert sur.train_X.shape == (10, 2)
    assert not np.any(np.all(sur.train_X == X[3], axis=1))
    assert not np.any(np.all(sur.train_X == X[7], axis=1))
    assert sur.model.train_inputs[0].shape[-2] == 10
    assert np.all(np.isfinite(sur.model.train_targets.numpy()))
    mean, std = sur.predict(X)
    assert mean.shape == (12, 2) and std.shape == (12, 2)
    ok = np.isfinite(Y).all(1)
    # minimisation units (the model itself maximises -y): predictions track the data
    assert np.corrcoef(mean[ok, 1], Y[ok, 1])[0, 1] > 0.95
    x = propose_ehvi(sur, X, Y, reference_point(Y), seed=0, search=AcqfSearch(2, 32))
    assert x.shape == (2,) and np.all((x >= 0) & (x <= 1))


def test_log_outcome_predicts_original_units():
    X = sobol(16, 1, seed=1)
    y = np.exp(6 * X[:, 0])  # spans orders of magnitude, positive
    sur = GPSurrogate(1, log_outcomes=[True]).fit(X, y)
    assert sur.offsets[0] == 0.0
    mean, std = sur.predict(X)
    np.testing.assert_allclose(mean[:, 0], y, rtol=0.1)
    assert np.all(std > 0)
    z = np.r_[0.0, y[1:]]  # a zero cost: shifted log, offset from the data range
    sur0 = GPSurrogate(1, log_outcomes=[True]).fit(X, z)
    assert sur0.offsets[0] == pytest.approx(0.01 * (z.max() - z.min()))


def test_cost_transform_round_trip():
    """t = -g(y) with g = shifted log on flagged outputs; a zero-width posterior maps back to
    the costs themselves."""
    Y = np.array([[0.0, -2.0], [5.0, 1.0], [50.0, 3.0]])
    tf = cost_transform([True, False]).fit(Y)
    T = tf.forward(Y)
    c = 0.01 * 50.0
    np.testing.assert_allclose(T, np.column_stack([-np.log(Y[:, 0] + c), -Y[:, 1]]))
    mean, std = tf.untransform(T, np.zeros_like(T))
    np.testing.assert_allclose(mean, Y, atol=1e-12)
    assert np.all(std == 0)


def test_group_offsets_recover_the_start_free_cost():
    """Six 'starts' shift the log cost by up to +-3: with groups the GP sees through them."""
    rng = np.random.default_rng(3)
    X = rng.uniform(size=(60, 2))
    h = 2.0 * ((X - 0.5) ** 2).sum(1)  # start-free log cost, range ~1
    b = np.array([-3.0, -1.0, 0.0, 0.5, 1.5, 2.0])
    g = np.arange(60) % 6
    y = np.exp(h + b[g] + 0.05 * rng.normal(size=60))
    Xt = rng.uniform(size=(200, 2))
    ht = 2.0 * ((Xt - 0.5) ** 2).sum(1)

    def error(sur):
        m, _ = sur.posterior_model_space(Xt)
        m = -m[:, 0]
        return np.sqrt(np.mean((m - m.mean() - (ht - ht.mean())) ** 2))

    plain = GPSurrogate(1, log_outcomes=[True]).fit(X, y)
    grouped = GPSurrogate(1, log_outcomes=[True], group_outputs=[True]).fit(X, y, groups=g)
    est = np.array([grouped.group_offsets[k][0] for k in range(6)])
    # model space is -log y: the offsets come out negated, centred
    np.testing.assert_allclose(-est, b - b.mean(), atol=0.25)
    assert error(grouped) < 0.1 < error(plain)
    # state round trip: restored before a fit, the same data give the same fit
    a = GPSurrogate(1, log_outcomes=[True], group_outputs=[True], refit_every=2, min_refit_n=5)
    a.fit(X[:54], y[:54], groups=g[:54])
    state = pickle.loads(pickle.dumps(a.state_dict()))
    a.fit(X, y, groups=g)
    b2 = GPSurrogate(1)
    b2.load_state_dict(state)
    b2.fit(X, y, groups=g)
    assert error(b2) == error(a)
    assert b2.group_offsets.keys() == a.group_offsets.keys()
    # each row's offset, and none for a row without a group
    rows = grouped.start_offsets(np.array([0, 5, -1]))
    np.testing.assert_array_equal(rows, [grouped.group_offsets[0], grouped.group_offsets[5], [0.0]])
    # no group information (-1 everywhere): plain model
    none = GPSurrogate(1, log_outcomes=[True], group_outputs=[True]).fit(X, y, groups=-np.ones(60))
    assert none.group_offsets == {}


def test_cost_samples_follow_the_posterior_in_cost_units():
    """Seeded posterior samples of the costs: their mean is the posterior mean of the cost
    (log-normal on a log output), joint samples of two nearby points move together."""
    X = sobol(16, 1, seed=1)
    y = np.exp(3 * X[:, 0]) * (1 + 0.05 * np.sin(20 * X[:, 0]))
    sur = GPSurrogate(1, log_outcomes=[True]).fit(X, y)
    Z = np.array([[0.2], [0.21], [0.8]])
    S = sur.cost_samples(Z, n_samples=4000, seed=3)
    assert S.shape == (4000, 3, 1)
    np.testing.assert_array_equal(S, sur.cost_samples(Z, n_samples=4000, seed=3))
    assert not np.array_equal(S, sur.cost_samples(Z, n_samples=4000, seed=4))
    mean, std = sur.predict(Z)
    np.testing.assert_allclose(S.mean(axis=0), mean, rtol=0.02)
    np.testing.assert_allclose(S.std(axis=0), std, rtol=0.1)
    J = sur.cost_samples(Z[:2], n_samples=2000, seed=3, joint=True)[:, :, 0]
    M = sur.cost_samples(Z[:2], n_samples=2000, seed=3)[:, :, 0]
    assert np.corrcoef(J.T)[0, 1] > 0.9 > abs(np.corrcoef(M.T)[0, 1])


def test_fast_posterior_matches_botorch():
    rng = np.random.default_rng(0)
    X = rng.uniform(size=(15, 3))
    Y = rng.normal(size=(15, 2))
    sur = GPSurrogate(2).fit(X, Y)
    assert isinstance(sur.model, SingleTaskGP)
    assert isinstance(sur.model.outcome_transform, Standardize)
    fm = ExactIndependentGP.from_singletask(sur.model)
    Xt = torch.rand(4, 3, 3, dtype=torch.float64)
    p1, p2 = sur.model.posterior(Xt), fm.posterior(Xt)
    torch.testing.assert_close(p1.mean, p2.mean)
    torch.testing.assert_close(
        p1.distribution.covariance_matrix, p2.distribution.covariance_matrix, atol=1e-9, rtol=1e-7
    )


def test_warm_start_refit_schedule():
    X = sobol(30, 2, seed=2)
    Y = (X**2).sum(1, keepdims=True)
    sur = GPSurrogate(1, refit_every=3, min_refit_n=20)
    full = [sur.fit(X[:n], Y[:n]).last_fit_was_full for n in (10, 15, 20, 21, 22, 23, 24, 25)]
    # n < 20: always; then one full fit every 3rd call counted from the last full fit
    assert full == [True, True, False, False, True, False, False, True]


def test_refit_period_grows_with_the_data():
    X = sobol(64, 2, seed=2)
    Y = (X**2).sum(1, keepdims=True)
    sur = GPSurrogate(1, refit_every=3, refit_fraction=0.1, min_refit_n=5)
    full = [n for n in range(40, 60) if sur.fit(X[:n], Y[:n]).last_fit_was_full]
    # period max(3, ceil(0.1 n)): 4 calls up to n = 40, 5 up to 50, then 6
    assert full == [40, 45, 50, 56]
    # the period is part of the state: a restored surrogate keeps it
    restored = GPSurrogate(1)
    restored.load_state_dict(sur.state_dict())
    assert restored.refit_fraction == 0.1 and restored.refit_every == 3


# ----------------------------------------------------------------------------- proposals
def toy_ei(X: np.ndarray) -> np.ndarray:
    """Cost with minimum 0 at (0.7, 0.3), min of the initial design well above it."""
    return ((X - np.array([0.7, 0.3])) ** 2).sum(1) + 0.1 * np.sin(8 * X[:, 0])


def test_ei_improves_on_initial_design():
    X = sobol(6, 2, seed=3)
    y = toy_ei(X)
    best0 = y.min()
    sur = GPSurrogate(1)
    for i in range(12):
        x = propose_ei(sur, X, y, seed=i, search=AcqfSearch(num_restarts=2, raw_samples=64))
        assert x.shape == (2,) and np.all((x >= 0) & (x <= 1))
        X = np.vstack([X, x])
        y = np.r_[y, toy_ei(x[None])]
    assert y.min() < best0 - 0.02
    assert y.min() < 0.0  # near the global basin (f* ~ -0.09)


def branin_currin(X: np.ndarray) -> np.ndarray:
    from botorch.test_functions.multi_objective import BraninCurrin

    # BoTorch's BraninCurrin is a minimisation problem with negate=False: costs as is
    return BraninCurrin(negate=False)(torch.as_tensor(X)).numpy()


def test_ehvi_increases_hypervolume():
    X = sobol(8, 2, seed=4)
    Y = branin_currin(X)
    ref = reference_point(Y)
    hv0 = hypervolume(Y, ref)
    sur = GPSurrogate(2, log_outcomes=[False, False])
    for i in range(10):
        x = propose_ehvi(
            sur,
            X,
            Y,
            ref,
            seed=i,
            options=EHVIOptions(mc_samples=32),
            search=AcqfSearch(num_restarts=2, raw_samples=64),
        )
        assert x.shape == (2,) and np.all((x >= 0) & (x <= 1))
        X = np.vstack([X, x])
        Y = np.vstack([Y, branin_currin(x[None])])
    # seeded run: ~1.77 hv0; 10 uniform random points give ~1.04 hv0
    assert hypervolume(Y, ref) > 1.3 * hv0
    assert pareto_mask(Y)[8:].any()  # new Pareto points were found


def test_ehvi_with_nothing_better_than_the_reference_point():
    """A reference point that no posterior mean beats (e.g. fixed from an early design that the
    model now judges worse) still gives a proposal: the whole box counts as improvement."""
    X = sobol(12, 3, seed=5)
    Y = np.stack([(X**2).sum(1), ((1 - X) ** 2).sum(1)], 1)
    ref = Y.min(axis=0) - 1.0
    x = propose_ehvi(GPSurrogate(2), X, Y, ref, seed=0, search=AcqfSearch(2, 32))
    assert x.shape == (3,) and np.all((x >= 0) & (x <= 1))


def test_state_dict_reproduces_next_proposal():
    X = sobol(25, 3, seed=5)
    Y = np.column_stack([((X - 0.2) ** 2).sum(1), ((X - 0.8) ** 2).sum(1)])
    ref = reference_point(Y[:10])
    sur = GPSurrogate(2, refit_every=4)
    for n in (22, 23):  # n >= 20: second call reuses hyperparameters
        sur.fit(X[:n], Y[:n])
    state = pickle.loads(pickle.dumps(sur.state_dict()))
    kw = dict(seed=11, options=EHVIOptions(mc_samples=16), search=AcqfSearch(2, 32))
    x1 = propose_ehvi(sur.fit(X, Y), X, Y, ref, **kw)
    sur2 = GPSurrogate(2)
    sur2.load_state_dict(state)
    x2 = propose_ehvi(sur2.fit(X, Y), X, Y, ref, **kw)
    np.testing.assert_array_equal(x1, x2)
    assert sur2.state_dict()["hyper"].keys() == sur.state_dict()["hyper"].keys()
    # and a different seed gives a different proposal (the check can fail)
    x3 = propose_ehvi(sur2, X, Y, ref, **{**kw, "seed": 12})
    assert not np.array_equal(x1, x3)
    # EI too (propose_ei fits the surrogate itself when its data changed)
    s1 = GPSurrogate(1, refit_every=5).fit(X[:22], Y[:22, :1])
    st = pickle.loads(pickle.dumps(s1.state_dict()))
    e1 = propose_ei(s1, X, Y[:, 0], seed=3, search=AcqfSearch(2, 32))
    s2 = GPSurrogate(1)
    s2.load_state_dict(st)
    e2 = propose_ei(s2, X, Y[:, 0], seed=3, search=AcqfSearch(2, 32))
    np.testing.assert_array_equal(e1, e2)


def test_ehvi_with_a_pruned_baseline_proposes_in_cube():
    """``max_baseline`` below the size of the front: the pruned front still gives a proposal
    in the cube."""
    X = sobol(10, 2, seed=6)
    Y = branin_currin(X)
    sur = GPSurrogate(2)
    options = EHVIOptions(mc_samples=16, max_baseline=2)
    x = propose_ehvi(
        sur, X, Y, reference_point(Y), seed=0, options=options, search=AcqfSearch(2, 32)
    )
    assert x.shape == (2,) and np.all((x >= 0) & (x <= 1))


def test_a_killed_builds_lock_is_cleared_and_a_live_build_is_waited_for(tmp_path):
    """BoTorch builds its fused EHVI kernel under a lock that torch waits for without end: a
    lock as old as STALE_BUILD_LOCK (a killed build's) is removed with a warning; a younger one
    is waited for until its build removes it, or until it is that old."""
    import os
    import subprocess
    import threading
    import time
    import warnings

    from mpcmobo.bo.acquisition import clear_dead_build_lock

    lock = tmp_path / "lock"
    assert clear_dead_build_lock(lock) is False  # none
    lock.write_text("")
    os.utime(lock, (time.time() - 200, time.time() - 200))
    with pytest.warns(RuntimeWarning, match="never finished"):
        assert clear_dead_build_lock(lock, stale=120) is True
    assert not lock.exists()
    lock.write_text("")  # a live build, done in 0.2 s
    threading.Timer(0.2, lock.unlink).start()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert clear_dead_build_lock(lock, stale=30, poll=0.05) is False
    lock.write_text("")  # a build killed just now: removed once it is 0.3 s old
    t0 = time.time()
    with pytest.warns(RuntimeWarning, match="never finished"):
        assert clear_dead_build_lock(lock, stale=0.3, poll=0.05) is True
    assert 0.25 <= time.time() - t0 < 5 and not lock.exists()
    lock.write_text("")  # an old lock whose build still compiles (a process works there)
    os.utime(lock, (time.time() - 200, time.time() - 200))
    compiler = subprocess.Popen(["sleep", "1"], cwd=tmp_path)
    t0 = time.time()
    with pytest.warns(RuntimeWarning, match="never finished"):
        assert clear_dead_build_lock(lock, stale=120, poll=0.05) is True
    assert compiler.poll() is not None and time.time() - t0 >= 0.5
