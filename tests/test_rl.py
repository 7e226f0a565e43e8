"""Tests of mpcmobo.rl: compatible critic, DPG gradient, objectives, exploration."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import scipy.linalg

from mpcmobo.experiment.loop import LearningRun
from mpcmobo.experiment.settings import SettingsError, load_settings
from mpcmobo.learners import make_learner
from mpcmobo.mpc import ParametricMPC
from mpcmobo.mpc.records import EpisodeRecord
from mpcmobo.rl import (
    CompatibleCritic,
    GaussianExploration,
    f1_closed_loop_cost,
    f2_optimality,
    f3_critic_drift,
    f4_lyapunov,
    mean_stage_cost,
    objectives,
)
from mpcmobo.systems import get_system


def _record(x=None, u=None, pi=None, V=None, dpi=None, dV=None, L=None, success=None, gamma=0.9):
    T = len(L)
    n_theta = dV.shape[1] if dV is not None else 1
    nu_dim = u.shape[1] if u is not None else 1
    return EpisodeRecord(
        x=np.zeros((T + 1, 2)) if x is None else x,
        u=np.zeros((T, nu_dim)) if u is None else u,
        pi=np.zeros((T, nu_dim)) if pi is None else pi,
        V=np.zeros(T + 1) if V is None else np.asarray(V, dtype=float),
        dpi=np.zeros((T, n_theta, nu_dim)) if dpi is None else dpi,
        dV=np.zeros((T + 1, n_theta)) if dV is None else dV,
        L=np.asarray(L, dtype=float),
        violation=np.zeros(T),
        slack=np.zeros(T),
        success=np.ones(T + 1, dtype=bool) if success is None else np.asarray(success, dtype=bool),
        theta=np.zeros(n_theta),
        gamma=gamma,
        status=["Solve_Succeeded"] * (T + 1),
    )


def synthetic(
    nu_true,
    w_true,
    rule="lstd",
    T=60,
    n_u=2,
    gamma=0.95,
    failed=(),
    scales=None,
    seed=0,
):
    """A record whose critic is known exactly.

    V^nu = V + dV nu_true; A_k = Psi_k^T w_true; L_k = V^nu_k + A_k - gamma * V_next, with
    V_next = V^nu_{k+1} (rule "lstd": Bellman equation for V^nu) or V_{k+1} (rule "paper": the
    paper's one-step rule). The exploration amplitudes are chosen so that sum_k phi_k A_k = 0 over
    the valid transitions, so both nu and w are exactly identifiable. Solves in ``failed`` get NaN
    MPC quantities and success False after L has been computed.
    """
    rng = np.random.default_rng(seed)
    n_theta = len(nu_true)
    s = np.ones(n_theta) if scales is None else np.asarray(scales, dtype=float)
    dV = rng.normal(size=(T + 1, n_theta)) * s
    V = 50.0 + 10.0 * rng.normal(size=T + 1)
    dpi = rng.normal(size=(T, n_theta, n_u)) * s[:, None]
    pi = rng.normal(size=(T, n_u))
    e = rng.normal(size=(T, n_u))
    g = np.einsum("kpa,ka,p->k", dpi, e, w_true)  # Psi_k^T w for unit amplitude
    bad = {k for j in failed for k in (j - 1, j) if 0 <= k < T}
    idx = np.array([k for k in range(T) if k not in bad])
    M = (dV[idx] * g[idx, None]).T  # (n_theta, n_valid): constraints sum phi_k c_k g_k = 0
    N = scipy.linalg.null_space(M)
    c = np.ones(T)
    c[idx] = N @ rng.normal(size=N.shape[1])
    c[idx] /= np.sqrt(np.mean(c[idx] ** 2))
    u = pi + c[:, None] * e
    A = np.einsum("kpa,ka,p->k", dpi, u - pi, w_true)
    V_nu = V + dV @ nu_true
    V_next = V_nu[1:] if rule == "lstd" else V[1:]
    L = V_nu[:-1] + A - gamma * V_next
    success = np.ones(T + 1, dtype=bool)
    for j in failed:
        success[j] = False
        V[j] = np.nan
        dV[j] = np.nan
        if j < T:
            dpi[j] = np.nan
    rec = _record(u=u, pi=pi, V=V, dpi=dpi, dV=dV, L=L, success=success, gamma=gamma)
    rec.x = rng.normal(size=(T + 1, 3))
    return rec, A


N_THETA = 5
NU_TRUE = np.array([0.3, -1.2, 0.7, 2.0, -0.5])
W_TRUE = np.array([1.5, 0.2, -0.8, 0.4, -2.0])


# ----------------------------------------------------------------------------- critic: recovery


@pytest.mark.parametrize("ridge", [0.0, 1e-12])
@pytest.mark.parametrize("method", ["lstd", "paper"])
def test_recovers_known_critic(method, ridge):
    rec, A = synthetic(NU_TRUE, W_TRUE, rule=method)
    res = CompatibleCritic(gamma=0.95, ridge=ridge, method=method).fit(rec)
    assert res.ok and res.nu_ok and res.w_ok
    assert res.valid_steps == rec.steps
    np.testing.assert_allclose(res.nu, NU_TRUE, rtol=0, atol=1e-6)
    np.testing.assert_allclose(res.w, W_TRUE, rtol=0, atol=1e-6)
    np.testing.assert_allclose(res.advantage, A, rtol=0, atol=1e-6)
    V_nu = rec.V + rec.dV @ NU_TRUE
    np.testing.assert_allclose(res.V_nu, V_nu, rtol=1e-9)
    assert res.Vc == pytest.approx(np.sum(V_nu), rel=1e-9)


def test_default_ridge_close_and_gamma_from_record():
    rec, _ = synthetic(NU_TRUE, W_TRUE, rule="lstd")
    res = CompatibleCritic(gamma=None).fit(rec)  # default ridge 1e-6, gamma from the record
    np.testing.assert_allclose(res.nu, NU_TRUE, atol=1e-4)
    np.testing.assert_allclose(res.w, W_TRUE, atol=1e-4)


def test_paper_rule_is_not_the_bellman_fixed_point():
    """On data satisfying the Bellman equation for V^nu, only the LSTD rule recovers nu."""
    rec, _ = synthetic(NU_TRUE, W_TRUE, rule="lstd")
    paper = CompatibleCritic(gamma=0.95, ridge=0.0, method="paper").fit(rec)
    lstd = CompatibleCritic(gamma=0.95, ridge=0.0, method="lstd").fit(rec)
    assert np.max(np.abs(paper.nu - NU_TRUE)) > 1e-2
    assert np.max(np.abs(lstd.nu - NU_TRUE)) < 1e-6
    # and with gamma = 0 the two rules coincide
    rec0, _ = synthetic(NU_TRUE, W_TRUE, rule="lstd", gamma=0.0)
    a = CompatibleCritic(gamma=0.0, ridge=0.0, method="paper").fit(rec0)
    b = CompatibleCritic(gamma=0.0, ridge=0.0, method="lstd").fit(rec0)
    np.testing.assert_allclose(a.nu, b.nu, atol=1e-9)


def test_q_target_choice_matters():
    """The LSTDQ target V_theta(x_{k+1}) vs V^nu(x_{k+1}): each is exact on its own data."""
    rec, _ = synthetic(NU_TRUE, W_TRUE, rule="lstd")
    good = CompatibleCritic(gamma=0.95, ridge=0.0, method="lstd", q_target="V_nu").fit(rec)
    bad = CompatibleCritic(gamma=0.95, ridge=0.0, method="lstd", q_target="V_theta").fit(rec)
    assert good.q_target == "V_nu" and bad.q_target == "V_theta"
    np.testing.assert_allclose(good.w, W_TRUE, atol=1e-6)
    assert np.max(np.abs(bad.w - W_TRUE)) > 1e-3
    assert CompatibleCritic(gamma=0.9, method="paper").q_target == "V_theta"


@pytest.mark.parametrize("method", ["lstd", "paper"])
def test_feature_scaling_across_orders_of_magnitude(method):
    scales = 10.0 ** np.array([-5.0, -2.0, 0.0, 3.0, 6.0])
    nu_true, w_true = NU_TRUE / scales, W_TRUE / scales  # comparable contributions
    rec, A = synthetic(nu_true, w_true, rule=method, scales=scales, seed=3)
    res = CompatibleCritic(gamma=0.95, ridge=1e-12, method=method).fit(rec)
    assert res.ok
    np.testing.assert_allclose(res.nu * scales, NU_TRUE, atol=1e-6)
    np.testing.assert_allclose(res.w * scales, W_TRUE, atol=1e-6)
    np.testing.assert_allclose(res.advantage, A, atol=1e-6)


# ----------------------------------------------------------------------------- critic: DPG


def test_dpg_gradient_matches_direct_computation():
    rec, _ = synthetic(NU_TRUE, W_TRUE, rule="lstd", T=40, n_u=3, seed=7)
    res = CompatibleCritic(gamma=0.95, ridge=0.0).fit(rec)
    T = rec.steps
    per_step = np.zeros((T, N_THETA))
    psi = np.zeros((T, N_THETA))
    for k in range(T):
        G = rec.dpi[k]  # (n_theta, nu)
        per_step[k] = G @ (G.T @ res.w)
        psi[k] = G @ (rec.u[k] - rec.pi[k])
    np.testing.assert_allclose(res.grad, per_step.sum(axis=0) / T, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(res.grad_norms, np.linalg.norm(per_step, axis=1), rtol=1e-10)
    np.testing.assert_allclose(res.advantage, psi @ res.w, rtol=1e-10, atol=1e-12)
    assert f2_optimality(res) == pytest.approx(np.mean(np.linalg.norm(per_step, axis=1)))
    assert res.mean_abs_advantage == pytest.approx(np.mean(np.abs(psi @ res.w)))


# ----------------------------------------------------------------------------- critic: robustness


@pytest.mark.parametrize("method", ["lstd", "paper"])
def test_failed_solves_are_masked(method):
    failed = (0, 7, 8, 30, 60)  # includes the first state and the final state x_T
    rec, A = synthetic(NU_TRUE, W_TRUE, rule=method, failed=failed, T=60)
    res = CompatibleCritic(gamma=0.95, ridge=0.0, method=method).fit(rec)
    bad = {0, 6, 7, 8, 29, 30, 59}
    assert res.ok
    assert res.valid_steps == 60 - len(bad)
    assert set(np.flatnonzero(~res.mask)) == bad
    np.testing.assert_allclose(res.nu, NU_TRUE, atol=1e-6)
    np.testing.assert_allclose(res.w, W_TRUE, atol=1e-6)
    for arr in (res.w, res.nu, res.grad, res.advantage, res.grad_norms):
        assert np.all(np.isfinite(arr))
    assert np.isfinite(res.Vc)
    assert set(np.flatnonzero(np.isnan(res.V_nu))) == set(failed)
    # steps without a policy sensitivity do not enter the gradient
    ok = res.policy_mask
    assert not ok[[0, 7, 8, 30]].any() and ok.sum() == 60 - 4
    direct = np.mean([rec.dpi[k] @ rec.dpi[k].T @ res.w for k in np.flatnonzero(ok)], axis=0)
    np.testing.assert_allclose(res.grad, direct, rtol=1e-10)


def test_failed_solve_with_finite_garbage_is_masked_by_success():
    rec, _ = synthetic(NU_TRUE, W_TRUE, rule="lstd", failed=(12,))
    rec.V[12] = 1e9  # a solver that returned a number although it failed
    rec.dV[12] = 1e7
    rec.dpi[12] = 3e5
    res = CompatibleCritic(gamma=0.95, ridge=0.0).fit(rec)
    np.testing.assert_allclose(res.nu, NU_TRUE, atol=1e-6)
    np.testing.assert_allclose(res.w, W_TRUE, atol=1e-6)
    # the garbage sensitivity of the failed solve stays out of the gradient and f2
    assert not res.policy_mask[12] and res.grad_norms[12] == 0.0
    keep = [k for k in range(rec.steps) if k != 12]
    direct = np.mean([rec.dpi[k] @ rec.dpi[k].T @ res.w for k in keep], axis=0)
    np.testing.assert_allclose(res.grad, direct, rtol=1e-10)


def test_nonfinite_stage_cost_masks_only_its_step():
    rec, _ = synthetic(NU_TRUE, W_TRUE, rule="lstd")
    L = rec.L.copy()
    full = CompatibleCritic(gamma=0.95, ridge=0.0).fit(rec)
    rec.L[5] = np.nan
    res = CompatibleCritic(gamma=0.95, ridge=0.0).fit(rec)
    assert res.valid_steps == full.valid_steps - 1 and not res.mask[5]
    assert np.all(np.isfinite(res.nu)) and np.all(np.isfinite(res.w))
    rec.L[:] = L  # restored: identical to the full fit
    np.testing.assert_allclose(CompatibleCritic(gamma=0.95, ridge=0.0).fit(rec).w, full.w)


def test_all_failed_gives_ok_false_and_finite_zeros():
    rec, _ = synthetic(NU_TRUE, W_TRUE, rule="lstd", T=20)
    rec.success[:] = False
    rec.V[:] = np.nan
    rec.dV[:] = np.nan
    rec.dpi[:] = np.nan
    res = CompatibleCritic(gamma=0.95).fit(rec)
    assert not res.ok and res.valid_steps == 0
    for arr in (res.w, res.grad, res.advantage, res.grad_norms, res.nu):
        assert np.all(arr == 0.0)
    assert res.w.shape == (N_THETA,) and res.advantage.shape == (20,)
    f = objectives(rec, res, previous_Vc=123.0)
    assert np.all(np.isfinite(f))
    assert f[1] == 0.0 and f[2] == 0.0 and f[3] == 0.0


def test_too_few_steps_and_no_exploration_give_ok_false():
    rec, _ = synthetic(NU_TRUE, W_TRUE, rule="lstd", T=20)
    rec.success[2:] = False  # only transition 0 -> 1 remains
    res = CompatibleCritic(gamma=0.95, min_valid_steps=2).fit(rec)
    assert res.valid_steps == 1 and not res.ok
    assert np.all(res.w == 0) and np.all(res.grad == 0)

    rec, _ = synthetic(NU_TRUE, W_TRUE, rule="lstd", T=20)
    rec.u = rec.pi.copy()  # no exploration: Psi = 0, w not identifiable
    res = CompatibleCritic(gamma=0.95).fit(rec)
    assert res.nu_ok and not res.w_ok and not res.ok
    assert np.all(res.w == 0) and np.all(res.advantage == 0) and np.all(res.grad == 0)
    assert np.all(np.isfinite(res.nu))


def test_bad_arguments():
    with pytest.raises(ValueError):
        CompatibleCritic(gamma=0.9, method="nope")
    with pytest.raises(ValueError):
        CompatibleCritic(gamma=0.9, q_target="nope")
    with pytest.raises(ValueError):
        CompatibleCritic(gamma=0.9, ridge=-1.0)
    with pytest.raises(ValueError, match="weighting"):
        CompatibleCritic(gamma=0.9, weighting="nope")


# ----------------------------------------------------------------------------- objectives


def test_f1_discounting_and_means():
    rec = _record(L=[1.0, 2.0, 3.0], gamma=0.5)
    expected = (1.0 + 0.5 * 2.0 + 0.25 * 3.0) / 3
    assert f1_closed_loop_cost(rec) == pytest.approx(expected)
    assert f1_closed_loop_cost(rec, gamma=1.0) == pytest.approx(2.0)
    assert mean_stage_cost(rec) == pytest.approx(2.0)
    rec.L[1] = np.inf
    assert np.isnan(f1_closed_loop_cost(rec))


def test_f3_first_episode_and_clipping():
    assert f3_critic_drift(10.0, None) == 0.0
    assert f3_critic_drift(10.0, 12.0) == 0.0  # decrease: clipped
    assert f3_critic_drift(12.0, 10.0) == pytest.approx(2.0)
    assert f3_critic_drift(np.nan, 10.0) == 0.0
    assert f3_critic_drift(10.0, np.nan) == 0.0


def test_f4_counts_only_increases():
    V = [5.0, 3.0, 4.0, 4.0, 10.0, np.nan, 0.0, 1.0]
    success = [True, True, True, True, True, False, True, True]
    rec = _record(V=V, L=np.zeros(7), success=success)
    # increases: 3->4 (1), 4->10 (6), 0->1 (1); pairs touching the failed solve are skipped
    assert f4_lyapunov(rec, beta=1.0) == pytest.approx(8.0)
    assert f4_lyapunov(rec, beta=2.5) == pytest.approx(20.0)
    rec.V[5] = -100.0  # finite, but the solve failed: still skipped
    assert f4_lyapunov(rec) == pytest.approx(8.0)
    dec = _record(V=[5.0, 4.0, 3.0, 1.0], L=np.zeros(3))
    assert f4_lyapunov(dec) == 0.0


def test_objectives_vector():
    rec, _ = synthetic(NU_TRUE, W_TRUE, rule="lstd", T=30)
    res = CompatibleCritic(gamma=0.95, ridge=0.0).fit(rec)
    f = objectives(rec, res, previous_Vc=res.Vc - 3.0, beta=0.5)
    assert f.shape == (4,)
    assert f[0] == pytest.approx(f1_closed_loop_cost(rec))
    assert f[1] == pytest.approx(np.mean(res.grad_norms)) and f[1] > 0
    assert f[2] == pytest.approx(3.0)
    assert f[3] == pytest.approx(0.5 * np.sum(np.maximum(0, np.diff(rec.V))))
    assert objectives(rec, res, previous_Vc=None)[2] == 0.0


# ----------------------------------------------------------------------------- exploration


def test_exploration_reproducible_and_decays():
    expl = GaussianExploration(std=[2.0, 0.5], decay=0.5, min_std=[0.3, 0.0])
    a = [expl.sample(np.random.default_rng(42), k) for k in range(3)]
    rng1, rng2 = np.random.default_rng(7), np.random.default_rng(7)
    s1 = np.array([expl.sample(rng1, k) for k in range(5)])
    s2 = np.array([expl.sample(rng2, k) for k in range(5)])
    np.testing.assert_array_equal(s1, s2)
    assert a[0].shape == (2,)
    z = np.random.default_rng(7).standard_normal((5, 2))
    np.testing.assert_allclose(s1, z * [2.0, 0.5])

    np.testing.assert_allclose(expl.std_at(0), [2.0, 0.5])
    np.testing.assert_allclose(expl.std_at(1), [1.0, 0.25])
    np.testing.assert_allclose(expl.std_at(3), [0.3, 0.0625])  # floor on the first input
    later = expl.at_episode(3)
    assert expl.episode == 0 and later.episode == 3
    np.testing.assert_allclose(later.sample(np.random.default_rng(7), 0), z[0] * [0.3, 0.0625])
    expl.episode = 1
    np.testing.assert_allclose(expl.std, [1.0, 0.25])

    # zero noise still consumes the generator: the random stream does not depend on the level
    zero = GaussianExploration(std=[0.0, 0.0])
    rng = np.random.default_rng(3)
    assert np.all(zero.sample(rng, 0) == 0.0)
    assert rng.standard_normal() == np.random.default_rng(3).standard_normal(3)[2]

    back = GaussianExploration.from_state_dict(later.state_dict())
    np.testing.assert_allclose(back.std, later.std)
    with pytest.raises(ValueError):
        GaussianExploration(std=[-1.0])
    with pytest.raises(ValueError):
        GaussianExploration(std=[1.0], decay=0.0)


# ----------------------------------------------------------------------------- end to end (LQ)


def _lq_episode(K, T, seed, a=0.9, b=0.5, R=0.1, Qx=1.0, gamma=0.9, a_model=0.8):
    """Scalar linear plant x+ = a x + b u + noise, policy u = -K x (theta = (K, c)).

    The "MPC" value is the exact value of the policy for a wrong model (a_model) plus a constant
    c: V_theta = P(K; a_model) x^2 + c, so V^nu can represent the true value of the policy.
    """

    def P(K, a):
        return (Qx + R * K**2) / (1 - gamma * (a - b * K) ** 2)

    def dP(K, a, h=1e-6):
        return (P(K + h, a) - P(K - h, a)) / (2 * h)

    rng = np.random.default_rng(seed)
    x, u, pi, L = np.zeros(T + 1), np.zeros(T), np.zeros(T), np.zeros(T)
    x[0] = rng.normal()
    for k in range(T):
        pi[k] = -K * x[k]
        u[k] = pi[k] + 0.3 * rng.normal()
        L[k] = Qx * x[k] ** 2 + R * u[k] ** 2
        x[k + 1] = a * x[k] + b * u[k] + 0.3 * rng.normal()
    rec = _record(
        x=x[:, None],
        u=u[:, None],
        pi=pi[:, None],
        V=P(K, a_model) * x**2 + 1.0,
        dV=np.stack([dP(K, a_model) * x**2, np.ones(T + 1)], axis=1),
        dpi=np.stack([-x[:-1], np.zeros(T)], axis=1)[:, :, None],
        L=L,
        gamma=gamma,
    )
    # DPG integrand with the true Q: grad pi * dQ/du = x^2 (1 - gamma (a - bK)^2) dP/dK (true a)
    expected = np.mean(x[:-1] ** 2) * (1 - gamma * (a - b * K) ** 2) * dP(K, a)
    return rec, expected


@pytest.mark.parametrize("K", [0.2, 0.5])
def test_default_critic_gradient_is_unbiased_on_lq_problem(K):
    """With a wrong-model V_theta, the default (LSTD, V^nu target) DPG matches the true gradient
    of the cost on average; its sign says to increase the gain (J decreases with K here)."""
    ratios = []
    for seed in range(10):
        rec, expected = _lq_episode(K, 2000, seed)
        res = CompatibleCritic(gamma=0.9).fit(rec)
        assert res.ok and res.grad[0] < 0 and expected < 0
        ratios.append(res.grad[0] / expected)
    assert 0.9 < np.mean(ratios) < 1.15


# ----------------------------------------------------------------------------- critic settings


def _critic_of(critic_settings):
    """The critic of a LearningRun built from ``settings.critic`` (as the study builds it)."""
    system = get_system("lq")
    mpc = ParametricMPC(system)
    learner = make_learner("mpc-rl", system.search_space, mpc.theta0)
    c = critic_settings
    run = LearningRun(
        system,
        learner,
        mpc,
        critic_ridge=c.ridge,
        critic_method=c.method,
        critic_q_target=c.q_target,
        critic_min_valid_steps=c.min_valid_steps,
        critic_weighting=c.weighting,
    )
    return run.critic


@pytest.mark.parametrize(
    "option, value, changed",
    [
        ("q_target", "V_theta", "w"),  # the default follows method "lstd": V_nu
        ("min_valid_steps", 25, "ok"),  # more than the 20 transitions: the fit fails
        ("weighting", "discounted", "grad"),
    ],
)
def test_critic_settings_reach_the_critic_and_change_its_result(option, value, changed):
    default = _critic_of(load_settings().critic)
    critic = _critic_of(load_settings(critic={option: value}).critic)
    assert getattr(critic, option) == value and getattr(default, option) != value
    rec, _ = synthetic(NU_TRUE, W_TRUE, rule="lstd", T=20)
    a, b = default.fit(rec), critic.fit(rec)
    assert a.ok
    assert not np.allclose(getattr(a, changed), getattr(b, changed))


@pytest.mark.parametrize(
    "option, value",
    [("q_target", "V"), ("min_valid_steps", 0), ("weighting", "geometric"), ("method", "lstdq")],
)
def test_bad_critic_settings_name_the_key(option, value):
    with pytest.raises(SettingsError, match=f"critic.{option}"):
        load_settings(critic={option: value})


# ------------------------------------------------------------- step rules (mpcmobo.rl.steps)


def test_adam_rule_follows_its_formula():
    """Adam's first step is lr * sign(g) (bias-corrected moments), then the running moments;
    the step's norm is clipped to max_step."""
    from mpcmobo.rl.steps import Adam

    g1, g2 = np.array([0.3, -2.0, 1e-3]), np.array([-0.1, -1.0, 2e-3])
    adam = Adam(lr=0.01, max_step=1e9)
    assert adam.coordinates == "unit"
    np.testing.assert_allclose(adam.step(g1), 0.01 * np.sign(g1), rtol=1e-4)  # eps
    m = 0.9 * 0.1 * g1 + 0.1 * g2
    v = 0.999 * 0.001 * g1**2 + 0.001 * g2**2
    expected = 0.01 * (m / (1 - 0.9**2)) / (np.sqrt(v / (1 - 0.999**2)) + 1e-8)
    np.testing.assert_allclose(adam.step(g2), expected, rtol=1e-9)
    assert adam.t == 2
    clipped = Adam(lr=0.5, max_step=0.1).step(g1)  # unclipped: 0.5 sign(g1), norm 0.87
    np.testing.assert_allclose(np.linalg.norm(clipped), 0.1)
    np.testing.assert_allclose(clipped / 0.1, np.sign(g1) / np.sqrt(3), rtol=1e-4)


def test_adam_state_round_trip_continues_the_same_steps():
    from mpcmobo.rl.steps import Adam

    rng = np.random.default_rng(0)
    a = Adam(lr=0.02, max_step=0.1)
    for _ in range(3):
        a.step(rng.normal(size=4))
    b = Adam(lr=0.02, max_step=0.1)
    b.load_state_dict(copy.deepcopy(a.state_dict()))
    g = rng.normal(size=4)
    np.testing.assert_array_equal(a.step(g), b.step(g))
    assert a.t == b.t == 4


def test_plain_gradient_rule_is_the_papers_constant_step():
    """``gd``: theta <- theta - lr grad in theta itself, the same lr at every step, no
    clipping."""
    from mpcmobo.rl.steps import PlainGradient

    rule = PlainGradient(lr=0.2)
    assert rule.coordinates == "theta"
    for g in (np.array([1.0, -2.0]), np.array([1e4, 0.5])):
        np.testing.assert_allclose(rule.step(g), 0.2 * g)
    assert rule.t == 2


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf")])
def test_step_rules_reject_bad_learning_rates(bad):
    from mpcmobo.rl.steps import Adam, PlainGradient

    for cls in (Adam, PlainGradient):
        with pytest.raises(ValueError, match="learning rate"):
            cls(lr=bad)
    with pytest.raises(ValueError, match="max_step"):
        Adam(max_step=0.0)
