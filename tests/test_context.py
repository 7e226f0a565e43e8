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
    safe = make_learner(
        "mobo", space, theta0, n_init=5, violation_budget="auto", contexts=spec, trust_region="off"
    )
    np.testing.assert_array_equal(safe.design[0], z0)
    assert np.max(np.abs(safe.design - z0)) <= 0.1 + 1e-12
    np.testing.assert_array_equal(safe.incumbent(), theta0)  # exactly theta0, no round trip
    # without a budget and without the trust region (the default since session 7, whose first
    # box of side 0.2 the design fills instead) the whole cube
    plain = make_learner(
        "mobo", space, theta0, n_init=5, violation_budget="off", trust_region="off"
    )
    assert np.max(np.abs(plain.design - z0)) > 0.3


def test_deploy_rule_verifies_a_candidate_before_it_deploys_it(rng):
    """deploy_min_runs: a better candidate with too few runs is proposed for verification,
    not deployed; with enough runs it is deployed, unless one of its own episodes did worse
    than the deployed theta would have from the same start (the paired check)."""
    sur, _, _ = _surrogate(rng, log=(True, True))
    C = np.linspace(0, 1, 4)[:, None]
    lo, hi = np.array([0.05, 0.5]), np.array([0.95, 0.5])
    rule = DeployRule(kappa=0.0, deploy_confidence=0.9, min_runs=3)
    Z = np.vstack([lo, hi])
    d = rule.decide(sur, Z, hi, C, None, 0, runs=lambda z: 2)
    np.testing.assert_array_equal(d.deployed, hi)
    np.testing.assert_array_equal(d.verify, lo)
    d = rule.decide(sur, Z, hi, C, None, 0, runs=lambda z: 3)
    np.testing.assert_array_equal(d.deployed, lo)
    assert d.verify is None
    d = rule.decide(sur, Z, hi, C, None, 0, runs=lambda z: 3, paired=lambda z, c: False)
    np.testing.assert_array_equal(d.deployed, hi)
    assert d.verify is None
    # choose() (used by MPC-RL) keeps its old meaning: no run count, no paired check
    np.testing.assert_array_equal(rule.choose(sur, Z, hi, C, None, 0), lo)
    with pytest.raises(ValueError, match="deploy_min_runs"):
        DeployRule(min_runs=0)


def test_gp_learners_deploy_only_thetas_run_deploy_min_runs_times(cstr, spec):
    """With the safe options, a theta is deployed only after verification episodes: the learner
    records them ("verify" in proposal_kinds_), and the deployed theta was run at least
    deploy_min_runs (3, its default) times, each episode better than theta0's."""
    space, theta0 = cstr.search_space, cstr.parameterization.theta0
    small = {k: v for k, v in SMALL.items() if k != "n_init"}
    lr = make_learner("bo", space, theta0, seed=0, contexts=spec, n_init=4, **small, **SAFE)
    rng = np.random.default_rng(0)
    z0 = space.to_unit(theta0)
    f1_of = {}
    for _ in range(16):
        th = lr.propose()
        z = space.to_unit(space.clip(th))
        # theta0's cost 1000; far better away from theta0 (a clear signal), same start noise
        f1 = 1000.0 * np.exp(-4 * np.linalg.norm(z - z0) + 0.05 * rng.normal())
        f1_of.setdefault(np.round(z, 9).tobytes(), []).append(f1)
        res = EpisodeResult(np.array([f1, 1, 0, 0]), np.zeros(14), True, x0=cstr.x0_lb)
        res.violation = 0.0
        lr.observe(th, res)
    assert "verify" in lr.proposal_kinds_ and lr.n_verifications >= 2
    inc = space.to_unit(lr.incumbent())
    assert not np.allclose(lr.incumbent(), theta0)  # it did learn
    assert len(f1_of[np.round(inc, 9).tobytes()]) >= 3


def test_runs_from_before_session_5_resume_with_the_values_of_their_time(cstr, spec):
    """The safe design is off by default. Switched on, it uses deploy_min_runs = 3 (and
    n_contexts = 8); a learner state written before session 5 (no "design" key) resumes with
    the values of that time for the options it left at their defaults (deploy_min_runs 1),
    while options set explicitly keep theirs."""
    space, theta0 = cstr.search_space, cstr.parameterization.theta0
    plain = make_learner("mobo", space, theta0, seed=1, contexts=spec, **SMALL)
    assert not plain.safe_mode and plain.context == "none" and plain.violation_budget is None
    assert plain.deploy_rule.deploy_confidence is None
    new = make_learner("mobo", space, theta0, seed=1, contexts=spec, **SMALL, **SAFE)
    assert new.safe_mode and new.context == "x0" and new.deploy_rule.min_runs == 3
    state = new.state_dict()
    again = make_learner("mobo", space, theta0, seed=1, contexts=spec, **SMALL, **SAFE)
    again.load_state_dict(state)
    assert again.context == "x0" and again.deploy_rule.min_runs == 3
    state.pop("design")
    old = make_learner("mobo", space, theta0, seed=1, contexts=spec, **SMALL, **SAFE)
    old.load_state_dict(state)
    assert old.context == "x0" and old.deploy_rule.deploy_confidence == 0.9
    assert old.deploy_rule.min_runs == 1  # did not exist before: its old value


def test_the_old_behaviour_is_reachable_by_options(cstr, spec):
    space, theta0 = cstr.search_space, cstr.parameterization.theta0
    off = {"context": "none", "violation_budget": "off", "deploy_confidence": 0.0}
    lr = make_learner("mobo", space, theta0, contexts=spec, deploy_min_runs=1, **off)
    assert not lr.safe_mode and lr.violation_budget is None
