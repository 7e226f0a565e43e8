"""The MPC's cost and plan against independent references.

* the paper's cost (section 5) recomputed from the returned plan equals ``sol.value``;
* the envelope theorem: dV/dtheta of every cost parameter is the partial derivative of that
  cost along the optimal plan (e.g. dV/dQ_jj = sum_i gamma^i (x_ij - x_rj)^2);
* the plan obeys a hand-written RK4 of the paper's model (eq. CSTR_Wrongmodel);
* on a linear system with the perfect model, inactive bounds and the discounted Riccati
  terminal weight, the MPC's policy is the LQR gain of ``scipy.linalg.solve_discrete_are``.

Everything here is at the study's MPC settings (``MPCSettings``: warm start, tol 1e-8), at a
state where an input bound and a slack are active.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg
from cstr_reference import hand_rk4

from mpcmobo.experiment.sections import MPCSettings
from mpcmobo.mpc import ParametricMPC
from mpcmobo.systems import System, get_system
from mpcmobo.systems.parameterization import MPCSpec

# A closed-loop start of the CSTR from which the imperfect MPC drives the temperature towards
# its lower bound: both inputs at their lower bound 55 and slacks active (found by a search of
# the constraint box; see test_the_chosen_states_have_active_bounds_and_slacks).
X_LOW_T = np.array([98.091, 0.069, 407.26])
# qc at its upper bound 140, qs inside its bounds, a slack active (cold solve at step 0)
X_HOT = np.array([93.04, 0.206, 455.697])


def _blocks(system, theta):
    b = system.parameterization.blocks
    return {k: np.asarray(theta[s]) for k, s in b.items()}


def _slack(system, x):
    """The smallest slack that relaxes the state bounds at x (eq. violation, eta >= 0)."""
    return np.maximum(0.0, system.x_lb - x) + np.maximum(0.0, x - system.x_ub)


def _paper_cost(system, N, gamma, Gamma, Gamma_f, theta, plan_x, plan_u):
    """The MPC cost of section 5 of the paper, written out, with G on [x_i, u_i] (absolute)."""
    t = _blocks(system, theta)
    nx = system.nx
    xr, ur = system.x_ref, system.u_ref
    cost = t["theta_c"][0]
    dxN = plan_x[N] - xr
    cost += gamma**N * (dxN @ (t["T"] * dxN) + Gamma_f @ _slack(system, plan_x[N]))
    for i in range(N + 1):  # sum_{i=0}^{N} G^T [x_i, u_i]; there is no u_N
        cost += t["G"][:nx] @ plan_x[i] + (t["G"][nx:] @ plan_u[i] if i < N else 0.0)
    for i in range(N):
        dx, du = plan_x[i] - xr, plan_u[i] - ur
        cost += gamma**i * (
            dx @ (t["Q"] * dx) + du @ (t["R"] * du) + Gamma @ _slack(system, plan_x[i])
        )
    return cost


def _constant_of_G(system, N, theta):
    """The documented difference of the code's cost (G on deviations) from the paper's (G on
    absolute values): sum_i G^T [x_r, u_r], a constant that does not change the policy."""
    t = _blocks(system, theta)
    nx = system.nx
    return (N + 1) * t["G"][:nx] @ system.x_ref + N * t["G"][nx:] @ system.u_ref


def _theta(mpc, seed):
    """A theta away from theta0 in every cost block (weights x e^N(0, 0.3^2), G ~ N(0, 3^2))."""
    rng = np.random.default_rng(seed)
    th = mpc.theta0 * np.exp(rng.normal(0, 0.3, mpc.n_theta))
    b = mpc.param.blocks
    th[b["theta_c"]] = 7.0
    th[b["G"]] = rng.normal(0, 3, b["G"].stop - b["G"].start)
    return th


@pytest.fixture(scope="module")
def study_mpc(cstr):
    """The imperfect CSTR MPC at the study's settings (warm start, tol 1e-8)."""
    return ParametricMPC(cstr, model="imperfect", **MPCSettings().options())


def _warm_solve(system, mpc, x0, theta, steps=1):
    """Closed loop from x0 for ``steps`` steps, then the warm-started solve at the state
    reached: what the study's episode computes there."""
    mpc.reset()
    x = x0
    for _ in range(steps):
        sol = mpc.solve(x, theta, sensitivities=False)
        x = system.plant_step(x, sol.action)
    return x, mpc.solve(x, theta)


@pytest.mark.parametrize("x0", [X_LOW_T, X_HOT], ids=["low-T", "hot"])
def test_value_is_the_papers_cost_of_the_returned_plan(cstr, study_mpc, x0):
    th = _theta(study_mpc, 7)
    x, sol = _warm_solve(cstr, study_mpc, x0, th)
    assert sol.success and sol.slack > 0.1  # a slack is active
    mpc = study_mpc
    cost = _paper_cost(
        cstr, mpc.N, mpc.gamma, mpc.problem.Gamma, mpc.problem.Gamma_f, th, sol.plan_x, sol.plan_u
    ) - _constant_of_G(cstr, mpc.N, th)
    # The cost above prices the slacks at the plan's violations. The solver stops at the
    # barrier parameter tau, where every slack stays slightly positive: its slacks exceed the
    # violations by ``excess`` in total (physical units), which adds at most
    # max(Gamma) * excess to the value (about 0.3 here, against values of 1e4 to 1e5).
    viol = sum(_slack(cstr, xi).sum() for xi in sol.plan_x)
    excess = sol.slack - viol
    assert 0 <= excess < 1e-4 * max(1.0, viol)
    gap = sol.value - cost
    eps = 1e-9 * abs(sol.value)
    assert -eps <= gap <= max(mpc.problem.Gamma.max(), mpc.problem.Gamma_f.max()) * excess + eps, (
        gap,
        excess,
    )
    # and the plan starts at the measured state
    np.testing.assert_array_equal(sol.plan_x[0], x)


@pytest.mark.parametrize("x0", [X_LOW_T, X_HOT], ids=["low-T", "hot"])
def test_value_gradient_is_the_envelope_of_the_cost(cstr, study_mpc, x0):
    """dV/dtheta_j = d(cost)/d(theta_j) at the fixed optimal plan (envelope theorem): for
    Q_jj the discounted sum of squared deviations along the plan, and so on for every block
    of the cost."""
    th = _theta(study_mpc, 7)
    _, sol = _warm_solve(cstr, study_mpc, x0, th)
    assert sol.success
    mpc, N, g = study_mpc, study_mpc.N, study_mpc.gamma
    X, U = sol.plan_x, sol.plan_u
    dX, dU = X - cstr.x_ref, U - cstr.u_ref
    disc = g ** np.arange(N)
    b = mpc.param.blocks
    expected = np.zeros(mpc.n_theta)
    expected[b["theta_c"]] = 1.0
    expected[b["T"]] = g**N * dX[N] ** 2
    expected[b["G"]] = np.r_[dX.sum(axis=0), dU.sum(axis=0)]  # deviations (module docstring)
    expected[b["Q"]] = disc @ dX[:N] ** 2
    expected[b["R"]] = disc @ dU**2
    scale = np.abs(expected)
    np.testing.assert_allclose(sol.dV_dtheta, expected, rtol=1e-5, atol=1e-7 * scale.max())


@pytest.mark.parametrize("x0", [X_LOW_T, X_HOT], ids=["low-T", "hot"])
def test_plan_follows_a_hand_rk4_of_the_imperfect_model(cstr, study_mpc, x0):
    _, sol = _warm_solve(cstr, study_mpc, x0, _theta(study_mpc, 7))
    assert sol.success
    mult = (1.1, 1.2, 1.15, 0.9, 1.2)  # eq. (CSTR_Wrongmodel)
    for i in range(study_mpc.N):
        pred = hand_rk4(sol.plan_x[i], sol.plan_u[i], mult)
        # equality constraints hold to IPOPT's tolerance in scaled units (half the box)
        err = np.abs(sol.plan_x[i + 1] - pred) / cstr.x_scale
        assert np.all(err < 1e-7), (i, err)
    assert np.all(sol.plan_u >= cstr.u_lb - 1e-9) and np.all(sol.plan_u <= cstr.u_ub + 1e-9)


def test_the_chosen_states_have_active_bounds_and_slacks(cstr, study_mpc):
    """The states of the tests above are what they claim: after one closed-loop step from
    X_LOW_T both inputs sit on their lower bound; from X_HOT (first, cold solve) q_c sits on its
    upper bound and q_s inside; slacks are active in both."""
    _, low = _warm_solve(cstr, study_mpc, X_LOW_T, study_mpc.theta0)
    np.testing.assert_allclose(low.action, cstr.u_lb, atol=1e-3)
    assert low.slack > 1.0
    study_mpc.reset()
    hot = study_mpc.solve(X_HOT, study_mpc.theta0)
    assert hot.action[1] == pytest.approx(cstr.u_ub[1], abs=1e-3)
    assert cstr.u_lb[0] + 1 < hot.action[0] < cstr.u_ub[0] - 1
    assert hot.slack > 0.1


# ----------------------------------------------------------------------------- LQR


def _decoupled_linear_system() -> System:
    """Two independent first-order plants, one unstable (a = 0.8) and one stable (a = -0.5),
    each driven by its own input: with a diagonal Q and R the discounted Riccati solution is
    diagonal, so it is a terminal weight the MPC's theta can express."""
    import casadi as ca

    def f(x, u, p):
        return ca.vertcat(p[0] * x[0] + p[2] * u[0], p[1] * x[1] + p[3] * u[1])

    spec = MPCSpec(horizon=5, gamma=0.9, Gamma=np.full(2, 1e3), Gamma_f=np.full(2, 1e3))
    return System(
        name="decoupled",
        state_names=("a", "b"),
        input_names=("ua", "ub"),
        dynamics=f,
        param_names=("a1", "a2", "b1", "b2"),
        true_params=np.array([0.8, -0.5, 1.0, 0.6]),
        models={"imperfect": np.array([0.5, -0.2, 0.8, 0.5])},
        dt=0.1,
        x_ref=np.zeros(2),
        u_ref=np.zeros(2),
        x_lb=np.full(2, -100.0),
        x_ub=np.full(2, 100.0),
        u_lb=np.full(2, -100.0),
        u_ub=np.full(2, 100.0),
        Q=np.array([1.0, 2.0]),
        R=np.array([0.1, 0.3]),
        Gamma=np.full(2, 1e3),
        x0_lb=np.full(2, -1.0),
        x0_ub=np.full(2, 1.0),
        mpc_spec=spec,
    )


def _rk4_matrices(a, b, dt):
    """x+ = A x + B u of one RK4 step of dx/dt = a x + b u (u held): the Taylor terms of RK4."""
    h = a * dt
    A = 1 + h + h**2 / 2 + h**3 / 6 + h**4 / 24
    B = dt * (1 + h / 2 + h**2 / 6 + h**3 / 24) * b
    return A, B


def test_mpc_policy_is_the_discounted_lqr_gain():
    s = _decoupled_linear_system()
    p = s.true_params
    A = np.diag([_rk4_matrices(p[0], p[2], s.dt)[0], _rk4_matrices(p[1], p[3], s.dt)[0]])
    B = np.diag([_rk4_matrices(p[0], p[2], s.dt)[1], _rk4_matrices(p[1], p[3], s.dt)[1]])
    # the hand RK4 matrices are the system's discretisation
    for e in np.eye(2):
        np.testing.assert_allclose(s.plant_step(e, np.zeros(2)), A @ e, rtol=1e-13)
        np.testing.assert_allclose(s.plant_step(np.zeros(2), e), B @ e, rtol=1e-13)
    gamma, Q, R = s.mpc_spec.gamma, np.diag(s.Q), np.diag(s.R)
    # discounted LQR = undiscounted LQR of (sqrt(gamma) A, sqrt(gamma) B)
    P = scipy.linalg.solve_discrete_are(np.sqrt(gamma) * A, np.sqrt(gamma) * B, Q, R)
    K = gamma * np.linalg.solve(R + gamma * B.T @ P @ B, B.T @ P @ A)
    assert np.allclose(P, np.diag(np.diag(P)))  # diagonal: a terminal weight theta can set
    mpc = ParametricMPC(s, model="perfect", **MPCSettings().options())
    th = mpc.theta0.copy()
    th[mpc.param.blocks["T"]] = np.diag(P)
    # V(0) is the slacks' barrier cost alone (every slack sits near tau, priced by Gamma)
    mpc.reset()
    V0 = mpc.solve(np.zeros(2), th).value
    assert 0 < V0 < mpc.problem.Gamma.max() * mpc.solve(np.zeros(2), th).slack
    rng = np.random.default_rng(0)
    mpc.reset()
    x = rng.uniform(-1, 1, 2)
    for _ in range(5):  # a closed loop: warm-started solves, as in the study
        sol = mpc.solve(x, th)
        assert sol.success
        np.testing.assert_allclose(sol.action, -K @ x, rtol=1e-5, atol=1e-7)
        # the optimal cost-to-go of the infinite-horizon problem: V = x^T P x (+ V(0))
        assert sol.value - V0 == pytest.approx(x @ P @ x, rel=1e-5, abs=1e-4)
        x = s.plant_step(x, sol.action + rng.normal(0, 0.1, 2))
    # with another terminal weight the finite-horizon policy is not the LQR gain
    th[mpc.param.blocks["T"]] = np.diag(Q)
    mpc.reset()
    x = np.array([0.7, -0.4])
    assert not np.allclose(mpc.solve(x, th).action, -K @ x, rtol=1e-3)


def test_perfect_model_mpc_predicts_with_the_perfect_model_when_the_model_is_learnable():
    """With learnable model parameters, theta carries the model: the default theta of the
    perfect-model MPC must carry the perfect model, so that J* is the perfect-model MPC's
    closed loop and not the imperfect one's (with the imperfect model, J* would be J_initial)."""
    from mpcmobo.experiment.evaluation import Evaluator

    plain = get_system("lq")
    s = get_system("lq", learn_model=("stiffness", "damping", "gain"))
    mpc = ParametricMPC(s, model="perfect")
    x = np.array([1.0, -0.5])
    sol = mpc.solve(x, None, sensitivities=False)
    np.testing.assert_allclose(sol.plan_x[1], s.plant_step(x, sol.plan_u[0]), atol=1e-7)
    imperfect = ParametricMPC(s, model="imperfect")
    np.testing.assert_array_equal(imperfect.theta0, s.parameterization.theta0)
    ev, ev_plain = Evaluator(s, n_starts=2, steps=10), Evaluator(plain, n_starts=2, steps=10)
    assert ev.J_star() == pytest.approx(ev_plain.J_star(), rel=1e-6)
    assert ev.J_star() < ev.J_eval(None)
