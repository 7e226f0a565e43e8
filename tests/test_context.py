"""Issue 11: the initial state as a context, the violation as a constraint, the deployment rule."""

import numpy as np
import pytest
import torch

from mpcmobo.bo import GPSurrogate
from mpcmobo.bo.context import (
    ContextExpectation,
    ContextModel,
    ContextSpec,
    expected_outcome_samples,
    violation_constraint,
)
from mpcmobo.experiment.loop import LearningRun
from mpcmobo.learners import EpisodeResult, make_learner
from mpcmobo.learners.deploy import DeployRule, default_budget
from mpcmobo.mpc import ParametricMPC
from mpcmobo.systems import get_system

SAFE = {"context": "x0", "violation_budget": "auto", "deploy_confidence": 0.9}
SMALL = {"n_init": 3, "num_restarts": 2, "raw_samples": 32, "maxiter": 10, "n_contexts": 4}


@pytest.fixture(scope="module")
def spec(cstr):
    return ContextSpec.from_system(cstr)


def test_context_spec_scales_to_the_initial_state_box(cstr, spec):
    c = spec.sample(16)
    assert c.shape == (16, 3) and np.all((c >= 0) & (c <= 1))
    np.testing.assert_allclose(spec.unit(cstr.x0_lb), 0.0)
    np.testing.assert_allclose(spec.unit(cstr.x0_ub), 1.0)
    # its own stream: not the evaluation starts (settings.evaluation.seed = 2025)
    ev = cstr.sample_initial_state(np.random.default_rng(2025))
    assert not np.any(np.all(np.isclose(spec.pool, ev), axis=1))
    with pytest.raises(ValueError, match="n_contexts"):
        spec.sample(0)


def test_context_expectation_averages_in_cost_space():
    """Log outputs t = -log(y + c) average as -log(mean(y + c)), identity outputs as means."""
    t = torch.tensor([[[-np.log(1.0), 1.0], [-np.log(9.0), 3.0]]], dtype=torch.float64)  # K = 2
    out = ContextExpectation(2, [True, False])(t)
    np.testing.assert_allclose(out.numpy()[0, 0], [-np.log(5.0), 2.0])
    keep = ContextExpectation(2, [True, False], keep=[1])(t)
    assert keep.shape[-1] == 1
    cons = violation_constraint(2, 1, False, 0.0, budget=1.5)(-t)  # expected violation 2
    np.testing.assert_allclose(cons.numpy(), [[0.5]])


def _surrogate(rng, n=40, log=(True,)):
    X = rng.uniform(size=(n, 3))  # (z1, z2, c)
    y = np.exp(2 * X[:, 0] + 1.5 * X[:, 2]) + 0.01 * rng.normal(size=n)
    Y = np.column_stack([y] + [X[:, 1] * 0.1 + 0.01] * (len(log) - 1))
    return GPSurrogate(len(log), log_outcomes=log).fit(X, Y), X, Y


def test_context_model_is_the_base_posterior_at_appended_points(rng):
    sur, _, _ = _surrogate(rng)
    C = np.array([[0.1], [0.5], [0.9]])
    z = torch.tensor([[[0.3, 0.6]]], dtype=torch.float64)  # 1 x 1 x 2
    post = ContextModel(sur.fast_model, C).posterior(z)
    Xa = torch.tensor([[[0.3, 0.6, c] for c in C[:, 0]]], dtype=torch.float64)
    ref = sur.fast_model.posterior(Xa)
    np.testing.assert_allclose(post.mean.numpy(), ref.mean.numpy())
    np.testing.assert_allclose(
        post.distribution.covariance_matrix.numpy(), ref.distribution.covariance_matrix.numpy()
    )


def test_expected_outcomes_integrate_the_contexts(rng):
    sur, _, _ = _surrogate(rng)
    C = np.linspace(0, 1, 8)[:, None]
    S = expected_outcome_samples(sur, np.array([[0.2, 0.5]]), C, n_samples=2000, seed=0)
    truth = np.mean(np.exp(2 * 0.2 + 1.5 * C[:, 0]))
    assert S.shape == (2000, 1, 1)
    assert abs(S.mean() - truth) < 0.1 * truth  # the mean over contexts, in cost space
    # not the cost at the mean context (the convex exp makes them differ by ~10%)
    assert abs(S.mean() - np.exp(2 * 0.2 + 1.5 * 0.5)) > 0.05 * truth


def test_deploy_rule_switches_only_with_evidence_and_never_to_unsafe(rng):
    sur, X, _ = _surrogate(rng, log=(True, True))
    C = np.linspace(0, 1, 4)[:, None]
    lo, hi = np.array([0.05, 0.5]), np.array([0.95, 0.5])
    # a clearly better theta (z1 small) replaces the current one
    rule = DeployRule(kappa=0.0, deploy_confidence=0.9)
    got = rule.choose(sur, np.vstack([lo, hi]), hi, C, budget=None, seed=0)
    np.testing.assert_array_equal(got, lo)
    # a theta that differs only where f1 does not depend on it: no evidence, the current stays
    near = np.array([0.95, 0.45])
    for current in (hi, near):
        got = rule.choose(sur, np.vstack([near, hi]), current, C, None, 0)
        np.testing.assert_array_equal(got, current)
    # the better theta violates (second output 0.1 z2 + 0.01 > budget at z2 = 0.9): not deployed
    bad = np.array([0.05, 0.9])
    got = rule.choose(sur, np.vstack([bad, hi]), hi, C, budget=0.08, seed=0)
    np.testing.assert_array_equal(got, hi)
    assert default_budget(1.5, 0.1) == pytest.approx(3.1)
    assert default_budget(np.nan, 0.1) == pytest.approx(0.1)


def _ctx_result(rng, cstr, z0=None, viol=0.0):
    f = np.abs(rng.normal(size=4)) * [1000, 10, 1, 100]
    return EpisodeResult(
        objectives=f,
        grad=rng.normal(size=14),
        critic_ok=True,
        x0=cstr.sample_initial_state(rng),
        violation=float(viol if z0 is None else viol),
    )


@pytest.mark.parametrize("name", ["mpc-rl", "bo", "mobo"])
def test_safe_contextual_learners_resume_exactly(cstr, spec, name):
    space, theta0 = cstr.search_space, cstr.parameterization.theta0
    kw = {"context": "x0", "deploy_confidence": 0.9, "n_contexts": 4}
    if name != "mpc-rl":
        kw = {**SMALL, **SAFE}
    a = make_learner(name, space, theta0, seed=3, contexts=spec, **kw)
    rng = np.random.default_rng(0)
    for _ in range(6):
        th = a.propose()
        assert space.contains(th)
        a.observe(th, _ctx_result(rng, cstr, viol=rng.exponential()))
    if name != "mpc-rl":
        assert a.budget_ is not None and a.budget_ >= spec.violation_floor
        assert a.surrogate.train_X.shape[1] == space.dim + 3  # (z, c)
    b = make_learner(name, space, theta0, seed=99, contexts=spec, **kw)
    b.load_state_dict(a.state_dict())
    np.testing.assert_array_equal(a.propose(), b.propose())
    np.testing.assert_array_equal(a.incumbent(), b.incumbent())


def test_old_checkpoints_load_into_the_new_options(cstr, spec):
    """A state written without contexts and violations (before issue 11) still loads."""
    space, theta0 = cstr.search_space, cstr.parameterization.theta0
    old = make_learner(
        "mobo", space, theta0, seed=1, **{k: v for k, v in SMALL.items() if k != "n_contexts"}
    )
    rng = np.random.default_rng(1)
    for _ in range(4):
        old.observe(old.propose(), _ctx_result(rng, cstr))
    state = old.state_dict()
    for key in ("contexts_x0", "violations", "violation_budget"):
        state.pop(key)
    again = make_learner(
        "mobo", space, theta0, seed=1, **{k: v for k, v in SMALL.items() if k != "n_contexts"}
    )
    again.load_state_dict(state)
    np.testing.assert_array_equal(old.propose(), again.propose())
    mpcrl = make_learner("mpc-rl", space, theta0, contexts=spec, deploy_confidence=0.9)
    plain = make_learner("mpc-rl", space, theta0).state_dict()
    mpcrl.load_state_dict(plain)
    np.testing.assert_array_equal(mpcrl.incumbent(), theta0)


def test_bad_options_are_named(cstr, spec):
    space, theta0 = cstr.search_space, cstr.parameterization.theta0
    with pytest.raises(ValueError, match="context"):
        make_learner("mobo", space, theta0, context="x1", contexts=spec)
    with pytest.raises(ValueError, match="violation_budget"):
        make_learner("mobo", space, theta0, violation_budget="lots", contexts=spec)
    with pytest.raises(ValueError, match="deploy_confidence"):
        make_learner("bo", space, theta0, deploy_confidence=1.5, contexts=spec)
    with pytest.raises(ValueError, match="ContextSpec"):
        make_learner("mobo", space, theta0, context="x0")


def test_mpc_rl_deploys_its_best_verified_theta_not_its_iterate(cstr, spec):
    """The iterate keeps stepping; the deployed theta is one the learner ran, and stays theta0
    until a run theta is confidently better."""
    space, theta0 = cstr.search_space, cstr.parameterization.theta0
    lr = make_learner("mpc-rl", space, theta0, contexts=spec, context="x0", deploy_confidence=0.9)
    rng = np.random.default_rng(0)
    for _ in range(6):
        th = lr.propose()
        f = [1000.0 * (1 + 0.05 * rng.normal()), 1, 0, 0]  # no theta is better than another
        lr.observe(th, EpisodeResult(np.array(f), np.ones(14), True, x0=cstr.x0_lb))
    assert not np.allclose(lr.propose(), theta0)  # the iterate moved
    np.testing.assert_allclose(lr.incumbent(), theta0)  # nothing verified better


def test_learning_run_passes_x0_and_violation_to_the_learner():
    s = get_system("lq")
    mpc = ParametricMPC(s)
    seen = []

    class Spy:
        name = "spy"

        def propose(self):
            return mpc.theta0.copy()

        def observe(self, theta, result):
            seen.append(result)

        def incumbent(self):
            return mpc.theta0.copy()

    run = LearningRun(s, Spy(), mpc, seed=0, steps=5)
    row, record = run.run_episode()
    np.testing.assert_array_equal(seen[0].x0, record.x[0])
    np.testing.assert_array_equal(seen[0].x0, row["x0"])
    assert seen[0].violation == pytest.approx(np.sum(record.violation))


def test_safe_design_starts_from_theta0_outward(cstr, spec):
    """With a violation budget the initial design is theta0 and points within trust_radius of
    it (unit cube); without one, global Sobol points."""
    space, theta0 = cstr.search_space, cstr.parameterization.theta0
    z0 = space.to_unit(theta0)
    safe = make_learner("mobo", space, theta0, n_init=5, violation_budget="auto", contexts=spec)
    np.testing.assert_array_equal(safe.design[0], z0)
    assert np.max(np.abs(safe.design - z0)) <= 0.1 + 1e-12
    np.testing.assert_array_equal(safe.incumbent(), theta0)  # exactly theta0, no round trip
    plain = make_learner("mobo", space, theta0, n_init=5)
    assert np.max(np.abs(plain.design - z0)) > 0.3
