"""The value of the EHVI acquisition against a brute-force Monte Carlo estimate.

The GPs of a mobo learner at its defaults (log f1 and f2, identity f3 and f4, one offset per
cycled start on the log outputs) are fitted to a synthetic 4-objective problem with per-start
effects. The acquisition of the next proposal is captured (BoTorch's ``optimize_acqf`` is
replaced by a stub), and ``exp(acquisition)`` at a few candidates is compared with

    E[ HV(P u {t}) - HV(P) ],  t ~ posterior of the GPs at the candidate,

estimated from 20 000 independent posterior draws of the BoTorch model, with the reference point
mapped by the cost transform written out here, ``P`` the non-dominated posterior means at the
observed points (found with ``moocore``), and each hypervolume from ``moocore``.

The pruning of that front (``posterior_front``) is compared with a greedy ranking by
``moocore.hv_contributions``: one point of least exclusive contribution removed at a time.
"""

from __future__ import annotations

import moocore
import numpy as np
import pytest
import torch

import mpcmobo.bo.acquisition as acquisition
from mpcmobo.bo import GPSurrogate, posterior_front, propose_ehvi, reference_point
from mpcmobo.learners import make_learner
from mpcmobo.systems import get_system

START_EFFECT = np.array([-0.8, 0.0, 0.8])  # log-cost offset of each cycled start


def _objectives(z, start, rng):
    """f1, f2 positive and spanning decades (log-modelled), f3, f4 often exactly 0."""
    b = START_EFFECT[start]
    f1 = np.exp(2.0 * np.sum((z - 0.3) ** 2) + b + 0.05 * rng.normal())
    f2 = np.exp(1.5 * np.sum((z - 0.7) ** 2) + 0.5 * b + 0.05 * rng.normal())
    f3 = max(0.0, np.sin(3 * z[0]) + 0.1 * rng.normal())
    f4 = max(0.0, z[1] - 0.5)
    return np.array([f1, f2, f3, f4])


def _cost_to_model(y, Y_train, log_flags):
    """The cost transform of the GPs, written out: t = -log(y + c) on the log outputs with
    c = 0 if the smallest training cost is positive, else -min + 1% of the range; t = -y on
    the others."""
    y = np.atleast_2d(np.asarray(y, float)).copy()
    for j in np.flatnonzero(log_flags):
        lo, hi = Y_train[:, j].min(), Y_train[:, j].max()
        c = 0.0 if lo > 0 else -lo + (0.01 * (hi - lo) if hi > lo else 1e-6)
        y[:, j] = np.log(y[:, j] + c)
    return -y


@pytest.fixture(scope="module")
def mobo_acquisition():
    """The GPs of a mobo learner at its defaults, fitted (one full fit) on 14 cycled-start
    episodes at seeded random points, and the acquisition of the next proposal with the
    learner's options (512 quasi-MC samples instead of 64, so that the acquisition's own
    sampling error is small), its reference point fixed from the first 6 as the learner does."""
    space = get_system("lq").search_space
    theta0 = get_system("lq").parameterization.theta0
    mobo = make_learner("mobo", space, theta0, seed=0, search={"mc_samples": 512})
    rng = np.random.default_rng(0)
    Z = rng.uniform(size=(14, space.dim))
    starts = np.arange(14) % 3
    Y = np.array([_objectives(z, g, rng) for z, g in zip(Z, starts)])
    ref = reference_point(Y[:6], margin=mobo.options.ref_margin)
    sur = mobo.surrogate.fit(Z, Y, groups=starts)
    captured = []

    def stub(acq_function, bounds, **kwargs):
        captured.append(acq_function)
        return torch.full((1, bounds.shape[1]), 0.5, dtype=bounds.dtype), torch.zeros(())

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(acquisition, "optimize_acqf", stub)
        for seed in range(8):  # 8 quasi-MC sample sets: their spread is the sampling error
            propose_ehvi(sur, Z, Y, ref, seed=seed, options=mobo.ehvi, search=mobo.search)
    assert len(captured) == 8
    return sur, Y, starts, ref, mobo.ehvi, captured


def test_defaults_reach_the_acquisition(mobo_acquisition):
    """mobo's defaults: log f1, f2 with one offset per start (the start effects of the data
    are recovered, in model units t = -log f), identity f3, f4; the acquisition's reference
    point is the learner's, mapped by the transform written out above."""
    sur, Y, starts, ref, _, acqs = mobo_acquisition
    acq = acqs[0]
    assert sur.log_outcomes == [True, True, False, False]
    assert sur.group_outputs == [True, True, False, False]
    b = np.array([sur.group_offsets[g] for g in range(3)])
    np.testing.assert_array_equal(b[:, 2:], 0.0)
    # f1's start effect is -0.8, 0, 0.8 in log cost: offsets near 0.8, 0, -0.8 in t = -log f1
    assert b[0, 0] > 0.4 and b[2, 0] < -0.4 and b[0, 0] > b[1, 0] > b[2, 0]
    # the GP is fitted on t minus its start's offset
    t = _cost_to_model(Y, Y, sur.log_outcomes) - b[starts]
    model = sur.model
    fitted = model.outcome_transform.untransform(model.train_targets.T)[0].detach().numpy()
    np.testing.assert_allclose(fitted, t, rtol=1e-10, atol=1e-10)
    tref = _cost_to_model(ref, Y, sur.log_outcomes)[0]
    np.testing.assert_allclose(acq.ref_point.numpy(), tref, rtol=1e-12)


def test_exp_acquisition_is_the_expected_hypervolume_improvement(mobo_acquisition):
    sur, Y, _, ref, options, acqs = mobo_acquisition
    tref = _cost_to_model(ref, Y, sur.log_outcomes)[0]
    X = torch.as_tensor(sur.train_X)
    with torch.no_grad():
        means = sur.model.posterior(X).mean.numpy()
    # minimisation view for moocore: costs -t, reference -tref
    C, r = -means, -tref
    on_front = moocore.is_nondominated(C) & np.all(C < r, axis=1)
    P = C[on_front]
    assert 4 <= len(P) <= options.max_baseline  # no pruning at this size
    hv_P = moocore.hypervolume(P, ref=r)
    rng = np.random.default_rng(1)
    # random points, and every point of the front (where each front point matters most)
    candidates = [rng.uniform(size=X.shape[1]) for _ in range(2)] + list(sur.train_X[on_front])
    n = 10_000
    for x in candidates:
        with torch.no_grad():
            values = [float(a(torch.as_tensor(x[None, None, :])).exp()) for a in acqs]
            post = sur.model.posterior(torch.as_tensor(x[None, :]))
            m, v = post.mean.numpy()[0], post.variance.numpy()[0]
        # the outputs are independent GPs: the posterior at one point is diagonal
        draws = -(m + np.sqrt(v) * rng.standard_normal((n, 4)))
        hvi = np.array(
            [
                moocore.hypervolume(np.vstack([P, s]), ref=r) - hv_P if np.all(s < r) else 0.0
                for s in draws
            ]
        )
        est, value = hvi.mean(), np.mean(values)
        # standard errors of the brute-force mean and of the mean over the 8 sample sets
        err = np.hypot(hvi.std() / np.sqrt(n), np.std(values, ddof=1) / np.sqrt(len(values)))
        assert est > 0
        assert abs(value - est) <= 4 * err + 1e-3 * est, (value, est, err)


# ----------------------------------------------------------------------------- pruning


def _greedy(C, r, keep):
    """Indices of C kept by removing, one at a time, the point of least exclusive hypervolume
    contribution (ties: the first), until ``keep`` remain."""
    idx = np.arange(len(C))
    while len(idx) > keep:
        contrib = moocore.hv_contributions(C[idx], ref=r)
        idx = np.delete(idx, int(np.argmin(contrib)))
    return idx


@pytest.fixture(scope="module")
def front_surrogate():
    """A GP on 40 points whose two costs trade off along a curved front (every posterior
    mean is non-dominated), so that pruning has to choose."""
    rng = np.random.default_rng(3)
    X = np.sort(rng.uniform(size=(40, 1)), axis=0)
    Y = np.column_stack([X[:, 0], (1 - X[:, 0]) ** 2 + 0.1 * np.sin(9 * X[:, 0]) ** 2])
    Y[:, 1] = np.maximum.accumulate(Y[::-1, 1])[::-1]  # make it a monotone trade-off
    sur = GPSurrogate(2, log_outcomes=[False, False]).fit(X, Y)
    return sur, X


@pytest.mark.parametrize("drop", [1, 3, 7, 15, 27])
def test_front_pruning_against_greedy_contributions(front_surrogate, drop):
    """Up to 7 points too many (one point dropped per round) the pruned front is exactly the
    greedy one; further above the cap (several dropped per round) it keeps at least 99.9% of
    the greedy front's hypervolume."""
    sur, X = front_surrogate
    means, _ = sur.posterior_model_space(X)
    C = -means
    r = C.max(axis=0) + 0.1
    tref = -r
    full = np.flatnonzero(moocore.is_nondominated(C) & np.all(C < r, axis=1))
    assert len(full) >= 30
    keep = len(full) - drop
    kept = posterior_front(sur, X, tref, max_baseline=keep)
    greedy = full[_greedy(C[full], r, keep)]
    assert len(kept) == keep
    if drop <= 7:
        np.testing.assert_array_equal(np.sort(kept), np.sort(greedy))
    hv_kept = moocore.hypervolume(C[kept], ref=r)
    hv_greedy = moocore.hypervolume(C[greedy], ref=r)
    assert hv_kept >= 0.999 * hv_greedy, (hv_kept, hv_greedy)


def _with_boxes_of(acq, cls, sampler):
    """A ``cls`` acquisition on ``acq``'s model and reference point with ``sampler`` and the
    same hypervolume boxes as ``acq`` (the captured acquisition of the fixture)."""
    new = cls(
        acq.model,
        ref_point=acq.ref_point,
        partitioning=acquisition.FastNondominatedPartitioning(
            ref_point=acq.ref_point, Y=torch.empty(0, 4, dtype=torch.float64)
        ),
        sampler=sampler,
    )
    new.cell_lower_bounds, new.cell_upper_bounds = acq.cell_lower_bounds, acq.cell_upper_bounds
    return new


def _value_and_grad(acqf, X0):
    """The acquisition's values at ``X0`` and the gradient of their sum."""
    X = X0.clone().requires_grad_(True)
    v = acqf(X)
    (g,) = torch.autograd.grad(v.sum(), X)
    return v, g


def test_single_point_shortcut_is_botorchs_logehvi_bit_for_bit(mobo_acquisition):
    """The q = 1 path of the acquisition (the fast path) gives BoTorch's own qLogEHVI values
    and gradients exactly, for one candidate per batch; q = 2 takes BoTorch's general code."""
    from botorch.acquisition.multi_objective.logei import qLogExpectedHypervolumeImprovement

    acq = mobo_acquisition[-1][0]
    assert isinstance(acq, acquisition._SingleLogEHVI)
    plain = _with_boxes_of(acq, qLogExpectedHypervolumeImprovement, acq.sampler)
    assert acq.cell_lower_bounds.shape[0] > 1
    d = acq.model.Xs.shape[-1]
    gen = torch.Generator().manual_seed(3)
    for shape in [(1, 1, d), (5, 1, d), (3, 2, d)]:
        X0 = torch.rand(*shape, generator=gen, dtype=torch.float64)
        (v1, g1), (v2, g2) = _value_and_grad(acq, X0), _value_and_grad(plain, X0)
        assert torch.equal(v1, v2), shape
        assert torch.equal(g1, g2), shape


def test_posterior_mean_alone_is_the_posterior_mean_bit_for_bit(mobo_acquisition):
    sur = mobo_acquisition[0]
    X = np.random.default_rng(2).uniform(size=(7, sur.train_X.shape[1]))
    mt, _ = sur.posterior_model_space(X)
    assert np.array_equal(sur.posterior_mean_model_space(X), mt)
