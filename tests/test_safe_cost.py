"""Issue 11, session 9: the safe design's cost at large n (the posterior at the observed thetas
once per fit, blocked posterior evaluation, the local fit ``local_fit``)."""

import numpy as np
import pytest

from mpcmobo.bo import GPSurrogate
from mpcmobo.bo import surrogate as surrogate_module
from mpcmobo.bo.context import ContextSpec, context_posterior, expected_outcome_means
from mpcmobo.learners import make_learner
from mpcmobo.learners.bo import local_rows
from mpcmobo.systems import get_system

SAFE = {"context": "x0", "violation_budget": "auto", "deploy_confidence": 0.9}
SMALL = {"n_init": 3, "num_restarts": 2, "raw_samples": 16, "maxiter": 5, "n_contexts": 4}


@pytest.fixture(scope="module")
def lq():
    return get_system("lq")


def _fitted(rng, n=15, d=3, dc=2, m=3):
    X = rng.uniform(size=(n, d + dc))
    Y = np.stack([np.sin(3 * X[:, 0]) + X[:, -1] + 2.0 + 0.05 * j for j in range(m)], 1)
    sur = GPSurrogate(m, log_outcomes=[True, False, True])
    return sur.fit(X, np.abs(Y) + 0.1), d


def test_the_posterior_at_observed_thetas_is_computed_once_per_fit(rng, monkeypatch):
    sur, d = _fitted(rng)
    C = rng.uniform(size=(4, 2))
    Z = rng.uniform(size=(7, d))
    calls = []
    real = GPSurrogate.posterior_model_space

    def counted(self, X):
        calls.append(len(X))
        return real(self, X)

    monkeypatch.setattr(GPSurrogate, "posterior_model_space", counted)
    mt, st = context_posterior(sur, Z, C)
    direct = real(sur, np.hstack([np.repeat(Z, 4, axis=0), np.tile(C, (7, 1))]))
    np.testing.assert_array_equal(mt, direct[0])
    np.testing.assert_array_equal(st, direct[1])
    # the shortlist, the safe points and the front ask again, for all thetas or a subset
    E, U = expected_outcome_means(sur, Z[[4, 1]], C, quantile=0.9)
    E2, U2 = expected_outcome_means(sur, Z, C, quantile=0.9)
    np.testing.assert_array_equal(E, E2[[4, 1]])
    np.testing.assert_array_equal(U, U2[[4, 1]])
    assert calls == [28]  # one evaluation of the 7 thetas x 4 contexts
    expected_outcome_means(sur, np.vstack([Z[:2], [[0.5] * d]]), C)
    assert calls == [28, 4]  # only the new theta
    sur.fit(sur.train_X, np.vstack([sur.train_Y[1:], sur.train_Y[:1]]))  # a new fit ...
    context_posterior(sur, Z[:1], C)
    assert calls == [28, 4, 4]  # ... forgets the old model's posterior


def test_the_posterior_in_blocks_is_that_of_one_block(rng, monkeypatch):
    sur, d = _fitted(rng)
    X = rng.uniform(size=(23, d + 2))
    whole = sur.posterior_model_space(X)
    monkeypatch.setattr(surrogate_module, "ROW_BLOCK", 5)
    blocks = sur.posterior_model_space(X)
    for a, b in zip(whole, blocks, strict=True):
        assert a.shape == b.shape == (23, 3)
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(sur.posterior_mean_model_space(X), whole[0], rtol=1e-12, atol=1e-12)


def test_local_rows_keep_theta0_and_the_nearest(rng):
    Z = np.array([[0.0], [0.9], [0.5], [0.45], [0.0], [0.52], [0.1], [0.6]])
    ok = np.array([True, True, True, True, True, False, True, True])
    theta0 = Z[:, 0] == 0.0
    np.testing.assert_array_equal(local_rows(Z, ok, np.array([0.5]), theta0, 10), ok)
    got = local_rows(Z, ok, np.array([0.5]), theta0, 4)
    # theta0's two episodes, then the nearest finite rows to 0.5 (row 5 is not finite)
    np.testing.assert_array_equal(np.flatnonzero(got), [0, 2, 3, 4])
    got = local_rows(Z, ok, np.array([0.5]), theta0, 5)
    np.testing.assert_array_equal(np.flatnonzero(got), [0, 2, 3, 4, 7])


def _observed(lq, rng, kw, n=24):
    """A learner that has observed ``n`` episodes (set directly, then one fit: cheap)."""
    space, theta0 = lq.search_space, lq.parameterization.theta0
    spec = ContextSpec.from_system(lq)
    a = make_learner("bo", space, theta0, seed=2, contexts=spec, **kw)
    z0 = space.to_unit(theta0)
    steps = rng.normal(size=(n, space.dim)) * (0.02 + 0.02 * np.arange(n))[:, None]
    Z = np.clip(z0 + steps, 0, 1)
    Z[::8] = z0  # theta0 run three times
    a.Z_ = Z
    a.Y_ = np.abs(rng.normal(size=(n, 1))) + 1.0
    a.grads_ = np.zeros((n, space.n_theta))
    a.starts_ = np.full(n, -1)
    a.C_ = spec.unit(np.array([lq.sample_initial_state(rng) for _ in range(n)]))
    a.V_ = rng.exponential(0.01, size=n)
    a.n_observed = n
    a._fit()
    return a, spec


def test_local_fit_fits_near_the_deployed_theta_and_resumes_exactly(lq, rng):
    space, theta0 = lq.search_space, lq.parameterization.theta0
    kw = {**SMALL, **SAFE, "local_fit": 20}
    a, spec = _observed(lq, rng, kw)
    X = a.surrogate.train_X
    assert X.shape[0] == 20  # the local fit: 20 of the 24 episodes
    z0 = space.to_unit(theta0)
    assert np.count_nonzero(np.all(X[:, : space.dim] == z0, axis=1)) == 3  # theta0's, all kept
    dist = np.linalg.norm(a.Z_ - a._pre_fit_incumbent, axis=1)
    used = np.array([np.any(np.all(X[:, : space.dim] == z, axis=1)) for z in a.Z_])
    assert dist[~used].min() >= dist[used & ~np.all(a.Z_ == z0, axis=1)].max()
    b = make_learner("bo", space, theta0, seed=7, contexts=spec, **kw)
    b.load_state_dict(a.state_dict())
    np.testing.assert_array_equal(b.surrogate.train_X, a.surrogate.train_X)
    np.testing.assert_array_equal(a.propose(), b.propose())
    np.testing.assert_array_equal(a.incumbent(), b.incumbent())
    full, _ = _observed(lq, np.random.default_rng(1234), {**SMALL, **SAFE})
    assert full.surrogate.train_X.shape[0] == 24  # unset: every episode


def test_bad_local_fit_is_named(lq):
    space, theta0 = lq.search_space, lq.parameterization.theta0
    spec = ContextSpec.from_system(lq)
    for bad in (5, 2.5, "300", True):
        with pytest.raises(ValueError, match="local_fit"):
            make_learner("mobo", space, theta0, contexts=spec, local_fit=bad, **SAFE)
    with pytest.raises(ValueError, match="local_fit applies to the safe design"):
        make_learner("mobo", space, theta0, contexts=spec, local_fit=300)
