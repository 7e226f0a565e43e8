"""The parametric MPC: sensitivities vs finite differences, closed loop, fallback, errors."""

import copy

import numpy as np
import pytest
import scipy.sparse.linalg
from cstr_reference import assert_warm_sensitivities_match_fd, fd_sensitivities

from mpcmobo.mpc import ParametricMPC, rollout
from mpcmobo.mpc.interior import Continuation, continuation, recentre
from mpcmobo.rl import GaussianExploration


def _random_theta(mpc, rng):
    th = mpc.theta0 * np.exp(rng.normal(0, 0.3, mpc.n_theta))
    th[0] = 0.0
    th[4:9] = rng.normal(0, 3, 5)
    return th


@pytest.fixture(scope="module")
def fd_mpc(cstr):
    # a tight tolerance and no warm start make the solver's output a smooth function of theta
    return ParametricMPC(cstr, model="imperfect", warm_start=False, tol=1e-10)


@pytest.mark.parametrize("trial", range(3))
def test_sensitivities_match_central_differences(cstr, fd_mpc, trial):
    rng = np.random.default_rng(100 + trial)
    mpc = fd_mpc
    x = cstr.sample_initial_state(rng)
    th = _random_theta(mpc, rng)
    sol = mpc.solve(x, th)
    assert sol.success
    # same active set on both sides: nothing crosses a bound by more than the barrier
    dpi, dV = fd_sensitivities(mpc, x, th)
    scale_pi = np.abs(dpi).max(axis=0)
    assert np.all(np.abs(sol.dpi_dtheta - dpi) <= 1e-4 * scale_pi + 1e-10)
    assert np.all(np.abs(sol.dV_dtheta - dV) <= 1e-4 * np.abs(dV) + 1e-6 * np.abs(dV).max())
    # theta_c changes the value by one and the policy not at all
    assert sol.dV_dtheta[0] == pytest.approx(1.0)
    np.testing.assert_allclose(sol.dpi_dtheta[0], 0.0, atol=1e-12)


def test_learnable_model_sensitivities(cstr):
    s = cstr.with_spec(learn_model=("k0", "k2"))
    mpc = ParametricMPC(s, warm_start=False, tol=1e-10)
    rng = np.random.default_rng(7)
    x = s.sample_initial_state(rng)
    th = mpc.theta0.copy()
    sol = mpc.solve(x, th)
    for i in (-2, -1):
        h = 1e-6
        tp, tm = th.copy(), th.copy()
        tp[i] += h
        tm[i] -= h
        fd = (mpc.solve(x, tp, False).action - mpc.solve(x, tm, False).action) / (2 * h)
        np.testing.assert_allclose(sol.dpi_dtheta[i], fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())


def test_perfect_model_beats_imperfect_in_closed_loop(cstr, cstr_mpc, cstr_perfect_mpc):
    rng = np.random.default_rng(0)
    starts = [cstr.sample_initial_state(rng) for _ in range(3)]
    cost = {}
    for name, mpc in (("imperfect", cstr_mpc), ("perfect", cstr_perfect_mpc)):
        cost[name] = np.mean(
            [rollout(cstr, mpc, None, x0, 60, sensitivities=False).L.mean() for x0 in starts]
        )
    assert cost["perfect"] < 0.5 * cost["imperfect"]


def test_solution_fields_and_shapes(cstr, cstr_mpc):
    sol = cstr_mpc.solve(cstr.x_ref, cstr_mpc.theta0)
    assert sol.success and sol.action.shape == (2,)
    assert sol.dpi_dtheta.shape == (14, 2) and sol.dV_dtheta.shape == (14,)
    assert np.all(sol.action >= cstr.u_lb) and np.all(sol.action <= cstr.u_ub)
    assert np.isfinite(sol.value) and sol.plan_u.shape == (10, 2)
    assert cstr_mpc.theta_names[0] == "theta_c" and cstr_mpc.theta0.shape == (14,)


def test_fallback_on_forced_solver_failure(cstr, monkeypatch):
    mpc = ParametricMPC(cstr, solver_options={"max_iter": 1}, warm_start=False)
    monkeypatch.setattr(mpc.solver, "cold_interior_point", lambda x, p: None)  # IPOPT alone
    sol = mpc.solve(np.array([100.0, 0.2, 420.0]), mpc.theta0)
    assert not sol.success and sol.fallback
    np.testing.assert_allclose(sol.action, cstr.u_ref)  # no plan yet: the reference input
    assert np.isnan(sol.value) and np.all(np.isnan(sol.dpi_dtheta))

    # after a good solve, a failure applies the shifted previous plan
    good = ParametricMPC(cstr)
    x = np.array([100.0, 0.2, 420.0])
    first = good.solve(x, good.theta0)
    monkeypatch.setattr(good.solver, "ipopt", lambda *a, **k: (False, "forced", 0, None, None))
    monkeypatch.setattr(good.solver, "newton", lambda p: None)  # the Newton steps fail too
    monkeypatch.setattr(good.solver, "interior_point", lambda p: None)  # and the continuation
    monkeypatch.setattr(good.solver, "restarted_interior_point", lambda p: None)  # restarted
    failed = good.solve(x, good.theta0)
    assert not failed.success
    np.testing.assert_allclose(failed.action, first.plan_u[1])

    # and an episode survives a solver that always fails
    rec = rollout(cstr, mpc, None, x, 5)
    assert rec.failures == 6 and np.all(np.isfinite(rec.x)) and np.all(np.isfinite(rec.L))


def test_episode_is_reproducible_with_a_seed(cstr, cstr_mpc):
    x0 = np.array([98.0, 0.15, 425.0])
    expl = GaussianExploration(std=np.array([2.0, 2.0]))
    a = rollout(cstr, cstr_mpc, None, x0, 15, rng=np.random.default_rng(5), exploration=expl)
    b = rollout(cstr, cstr_mpc, None, x0, 15, rng=np.random.default_rng(5), exploration=expl)
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.u, b.u)
    np.testing.assert_allclose(a.dpi, b.dpi)
    assert not np.allclose(a.u, a.pi)  # exploration was applied
    assert a.x.shape == (16, 3) and a.dV.shape == (16, 14) and a.dpi.shape == (15, 14, 2)


def test_bad_inputs(cstr, cstr_mpc):
    with pytest.raises(ValueError, match="shape"):
        cstr_mpc.solve(np.zeros(2), cstr_mpc.theta0)
    with pytest.raises(ValueError, match="NaN"):
        cstr_mpc.solve(np.array([100, np.nan, 430]), cstr_mpc.theta0)
    with pytest.raises(ValueError, match=r"theta has shape \(13,\)"):
        cstr_mpc.solve(cstr.x_ref, np.ones(13))
    with pytest.raises(ValueError, match="NaN"):
        cstr_mpc.solve(cstr.x_ref, np.full(14, np.nan))
    with pytest.raises(ValueError, match="rng"):
        rollout(cstr, cstr_mpc, None, cstr.x_ref, 3, exploration=GaussianExploration(std=[1, 1]))


def _splu_sensitivities(mpc, x, theta):
    """dpi/dtheta, dV/dtheta by SciPy's sparse LU on the forward KKT system (eq. nabla_pi):
    dy/dtheta = -(dR/dy)^-1 dR/dtheta, one factorisation, n_theta right-hand sides."""
    p = np.concatenate([x, theta])
    ok, _, _, out, w = mpc.solver.ipopt(x, p, False)
    assert ok
    lam_g, lam_x = np.asarray(out["lam_g"]).ravel(), np.asarray(out["lam_x"]).ravel()
    pr = mpc.problem
    Jy, Jth, dfdth, dfdw = mpc.kkt.kkt(w, *mpc.kkt.multipliers(w, lam_g, lam_x), p)
    dw = scipy.sparse.linalg.splu(Jy.sparse()).solve(-Jth.full())[: pr.nw]
    dpi = (pr.Su[:, None] * dw[pr.iu[0]]).T
    dV = pr.cost_scale * (dfdth.full().ravel() + dfdw.full().ravel() @ dw)
    return dpi, dV


def test_sensitivity_linear_solvers_agree(cstr, fd_mpc):
    # the default adjoint sparse-QR path, CasADi's csparse, and SciPy's LU of the forward system
    other = ParametricMPC(cstr, model="imperfect", warm_start=False, tol=1e-10, linsol="csparse")
    rng = np.random.default_rng(11)
    x = cstr.sample_initial_state(rng)
    th = _random_theta(fd_mpc, rng)
    a, b = fd_mpc.solve(x, th), other.solve(x, th)
    assert a.success and b.success
    np.testing.assert_allclose(b.action, a.action, rtol=1e-10, atol=1e-10)
    splu_dpi, splu_dV = _splu_sensitivities(fd_mpc, x, th)
    for dpi, dV in ((b.dpi_dtheta, b.dV_dtheta), (splu_dpi, splu_dV)):
        np.testing.assert_allclose(dpi, a.dpi_dtheta, rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(dV, a.dV_dtheta, rtol=1e-7, atol=1e-9)
    with pytest.raises(ValueError, match="linsol 'splu'"):
        ParametricMPC(cstr, linsol="splu")


def test_warm_start_shifts_primal_and_dual(cstr):
    mpc = ParametricMPC(cstr)
    x = np.array([100.0, 0.2, 420.0])
    first = mpc.solve(x, mpc.theta0, False)
    prev, pr = mpc.solver.prev, mpc.problem
    np.testing.assert_allclose(
        mpc.system.u_ref + pr.Su * prev["w_shift"][pr.iu[0]], first.plan_u[1]
    )
    assert prev["lam_g"].shape == (pr.neq + pr.nin,) and prev["lam_x"].shape == (pr.nw,)
    second = mpc.solve(cstr.plant_step(x, first.action), mpc.theta0)
    assert second.success and second.iterations < 12


def _closed_loop_pairs(cstr, a, b, x, theta, steps):
    """Solve with both MPCs along the closed loop of ``a``; yield both solutions."""
    a.reset()
    b.reset()
    for _ in range(steps):
        sa, sb = a.solve(x, theta), b.solve(x, theta)
        yield sa, sb
        x = cstr.plant_step(x, sa.action)


def _active_theta(mpc):
    """theta0 with a linear cost on q_c that holds q_c at its lower bound (an active bound)."""
    th = mpc.theta0.copy()
    th[mpc.theta_names.index("G_qc")] = 3000.0
    return th


@pytest.mark.parametrize("active", [False, True])
def test_newton_path_gives_the_ipopt_solution(cstr, active):
    ipopt = ParametricMPC(cstr, newton_steps=0)
    newton = ParametricMPC(cstr, newton_steps=6)
    x = np.array([100.0, 0.15, 430.0])
    theta = _active_theta(newton) if active else newton.theta0
    used = 0
    for sa, sb in _closed_loop_pairs(cstr, ipopt, newton, x, theta, 25):
        if active:
            assert sa.plan_u[:, 1].min() < cstr.u_lb[1] + 1e-3
        assert sa.success and sb.success and sa.status != "Newton_Succeeded"
        used += sb.status == "Newton_Succeeded"
        np.testing.assert_allclose(sb.action, sa.action, rtol=0, atol=1e-5)
        np.testing.assert_allclose(sb.value, sa.value, rtol=1e-7)
        scale = np.abs(sa.dpi_dtheta).max(axis=0)
        assert np.all(np.abs(sb.dpi_dtheta - sa.dpi_dtheta) <= 1e-4 * scale)
        np.testing.assert_allclose(sb.dV_dtheta, sa.dV_dtheta, rtol=1e-4, atol=1e-6)
    assert used >= 10  # the warm steps of the calm phase take the Newton path


def test_newton_sensitivities_match_central_differences(cstr):
    mpc = ParametricMPC(cstr, newton_steps=6)
    x = np.array([100.0, 0.15, 430.0])
    th = _active_theta(mpc)  # q_c held at its bound: the multipliers of that bound matter
    for _ in range(5):  # a few closed-loop steps: a warm start
        x = cstr.plant_step(x, mpc.solve(x, th, False).action)
    assert_warm_sensitivities_match_fd(mpc, x, th, "Newton_Succeeded")


def test_newton_steps_must_be_a_count(cstr):
    with pytest.raises(ValueError, match="newton_steps must be an integer >= 0, got -1"):
        ParametricMPC(cstr, newton_steps=-1)
    with pytest.raises(ValueError, match="continuation_steps must be an integer >= 0, got 1.5"):
        ParametricMPC(cstr, continuation_steps=1.5)


def _continuation_state(cstr, mpc, theta):
    """A closed-loop state of ``mpc`` whose warm solve takes the continuation, with the warm
    start it takes it from (the shifted plan of the solve before)."""
    x = cstr.sample_initial_state(np.random.default_rng(0))
    for _ in range(10):
        prev = copy.deepcopy(mpc.solver.prev)
        sol = mpc.solve(x, theta, False)
        if sol.status == "Continuation_Succeeded":
            return x, prev
        x = cstr.plant_step(x, sol.action)
    raise AssertionError("no step took the continuation")


def test_continuation_reaches_the_root_ipopt_stops_at(cstr, monkeypatch):
    # where the Newton steps cannot start (the new state violates the shifted plan), the
    # continuation solves: the same policy, value and sensitivities as IPOPT from that start
    mpc = ParametricMPC(cstr, continuation_steps=30)
    ipopt = ParametricMPC(cstr, continuation_steps=0)
    x, prev = _continuation_state(cstr, mpc, mpc.theta0)
    mpc.solver.prev, ipopt.solver.prev = copy.deepcopy(prev), copy.deepcopy(prev)
    a, b = mpc.solve(x, mpc.theta0), ipopt.solve(x, mpc.theta0)
    assert a.status == "Continuation_Succeeded" and b.status == "Solve_Succeeded"
    np.testing.assert_allclose(a.action, b.action, rtol=0, atol=1e-5)
    np.testing.assert_allclose(a.value, b.value, rtol=1e-7)
    assert np.all(np.abs(a.dpi_dtheta - b.dpi_dtheta) <= 1e-4 * np.abs(b.dpi_dtheta).max(axis=0))
    mpc.solver.prev = prev
    assert_warm_sensitivities_match_fd(mpc, x, mpc.theta0, "Continuation_Succeeded")
    # where it does not get there, the continuation restarted from the shifted plan on the
    # central path reaches the same root
    mpc.solver.prev = copy.deepcopy(prev)
    with monkeypatch.context() as m:
        m.setattr(mpc.solver, "interior_point", lambda p: None)
        r = mpc.solve(x, mpc.theta0)
    assert r.status == "Restart_Continuation_Succeeded"
    np.testing.assert_allclose(r.action, b.action, rtol=0, atol=1e-5)
    np.testing.assert_allclose(r.value, b.value, rtol=1e-7)
    # continuations that do not get there hand over to IPOPT
    mpc.solver.prev = copy.deepcopy(prev)
    monkeypatch.setattr(mpc.solver, "interior", Continuation(max_steps=1))
    assert mpc.solve(x, mpc.theta0).status == "Solve_Succeeded"


def test_a_continuation_that_ends_at_a_saddle_point_hands_over(cstr):
    # from a re-centred warm start the continuation can end at a saddle point of the barrier
    # problem (on this hot start of the CSTR, at four steps), dearer than the minimum IPOPT
    # finds from the same warm start: refused, the continuation restarted from the shifted
    # plan or IPOPT solves; every root accepted is a minimum
    mpc, ipopt = ParametricMPC(cstr), ParametricMPC(cstr, continuation_steps=0)
    rng = np.random.default_rng(2025)
    x = [cstr.sample_initial_state(rng) for _ in range(4)][3]  # J_eval's fourth start
    saddles = restarted = same = 0
    for _ in range(45):
        prev = copy.deepcopy(mpc.solver.prev)
        p = np.concatenate([x, mpc.theta0])
        raw = None
        if prev is not None and mpc.solver.newton(p) is None:  # the unchecked continuation
            lam, mu = mpc.kkt.multipliers(prev["w_shift"], prev["lam_g"], prev["lam_x"])
            y = recentre(mpc.kkt, prev["w_shift"], lam, mu, p, mpc.solver.interior)
            raw = continuation(mpc.kkt, y, p, 1e-8, mpc.solver.interior)
        sol = mpc.solve(x, mpc.theta0, False)
        if sol.status == "Continuation_Succeeded":
            assert raw is not None and mpc.kkt.is_minimum(raw[0], p)
        elif raw is not None and not mpc.kkt.is_minimum(raw[0], p):
            saddles += 1
            ipopt.solver.prev = prev
            ref = ipopt.solve(x, mpc.theta0, False)
            assert ref.value < raw[1] * mpc.problem.cost_scale  # the saddle is dearer
            if sol.status == "Restart_Continuation_Succeeded":  # a minimum, cheaper than it
                restarted += 1
                assert sol.value < raw[1] * mpc.problem.cost_scale
                # mostly IPOPT's minimum; here once another one, 8% dearer
                same += bool(np.abs(sol.action - ref.action).max() <= 1e-6)
            else:
                assert sol.status == ref.status == "Solve_Succeeded"
                np.testing.assert_allclose(sol.action, ref.action, rtol=0, atol=1e-6)
        x = cstr.plant_step(x, sol.action)
    assert saddles >= 2 and restarted >= 2 and same >= 2  # here: 4, 3 and 2


def test_cold_continuation_reaches_the_root_ipopt_stops_at(cstr, monkeypatch):
    # without a warm start the continuation starts from the cold guess on the central path:
    # the policy, value and sensitivities of IPOPT's cold solve, on most states of the box
    mpc, ipopt = ParametricMPC(cstr), ParametricMPC(cstr, continuation_steps=0)
    rng = np.random.default_rng(3)
    taken = 0
    for _ in range(8):
        x = cstr.sample_initial_state(rng)
        mpc.reset()
        ipopt.reset()
        a, b = mpc.solve(x, mpc.theta0), ipopt.solve(x, mpc.theta0)
        assert a.success and b.success
        if a.status != "Cold_Continuation_Succeeded":
            continue
        taken += 1
        np.testing.assert_allclose(a.action, b.action, rtol=0, atol=1e-5)
        np.testing.assert_allclose(a.value, b.value, rtol=1e-7)
        scale = np.abs(b.dpi_dtheta).max(axis=0)
        assert np.all(np.abs(a.dpi_dtheta - b.dpi_dtheta) <= 1e-4 * scale)
        np.testing.assert_allclose(a.dV_dtheta, b.dV_dtheta, rtol=1e-4, atol=1e-6)
    assert taken >= 6
    # without the continuation settings, or where it does not get there, IPOPT solves cold
    mpc.reset()
    monkeypatch.setattr(mpc.solver, "interior", Continuation(max_steps=1))
    assert mpc.solve(x, mpc.theta0).status == "Solve_Succeeded"


def test_numpy_call_gives_the_function_outputs_bit_for_bit():
    # the buffer-based call of the Newton and sensitivity functions: the numbers of
    # the CasADi call itself, in its shapes (a matrix, a scalar, a structurally sparse output)
    import casadi as ca

    from mpcmobo.mpc.kkt import NumpyCall

    a, b = ca.MX.sym("a", 3), ca.MX.sym("b", 2)
    fn = ca.Function(
        "f", [a, b], [ca.sin(a) * b[0], ca.dot(a, a) + b[1], ca.mtimes(a, b.T), ca.tril(a @ a.T)]
    )
    call = NumpyCall(fn)
    rng = np.random.default_rng(0)
    for _ in range(3):  # the buffers are reused
        x, y = rng.normal(size=3), rng.normal(size=2)
        got, want = call(x, y), fn(x, y)
        assert isinstance(got[1], float) and got[1] == float(want[1])
        for g, w in zip(got[:1] + got[2:], want[:1] + want[2:]):
            assert g.shape == w.shape and np.array_equal(g, np.asarray(w))
