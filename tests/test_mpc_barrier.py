"""The barrier path of warm solves (``barrier_steps``): a state that violates a state bound of
the shifted plan, the same solution as IPOPT, exact sensitivities, the fallbacks, settings."""

import numpy as np
import pytest
from cstr_reference import assert_warm_sensitivities_match_fd

from mpcmobo.experiment.rundir import RunDirectory
from mpcmobo.experiment.settings import Settings, settings_to_toml
from mpcmobo.mpc import ParametricMPC

X_CALM = np.array([100.0, 0.15, 430.0])
# C_A below its lower bound (90): the shifted plan's stage-0 row is violated, so the Newton
# steps at tau cannot start (not interior) and the barrier path solves
X_VIOLATING = [np.array([89.0, 0.15, 430.0]), np.array([88.0, 0.2, 425.0])]


@pytest.fixture(scope="module")
def pair(cstr):
    """(IPOPT only, the default MPC)."""
    return ParametricMPC(cstr, newton_steps=0, barrier_steps=0), ParametricMPC(
        cstr, barrier_steps=30
    )


def _warm(cstr, mpc, theta):
    """Two closed-loop steps from X_CALM: a warm start for the next solve."""
    mpc.reset()
    x = X_CALM
    for _ in range(2):
        x = cstr.plant_step(x, mpc.solve(x, theta, False).action)


@pytest.mark.parametrize("x", X_VIOLATING, ids=["C_A=89", "C_A=88"])
def test_barrier_path_gives_the_ipopt_solution(cstr, pair, x):
    ipopt, mpc = pair
    for m in pair:
        _warm(cstr, m, m.theta0)
    sa, sb = ipopt.solve(x, ipopt.theta0), mpc.solve(x, mpc.theta0)
    assert sa.success and sa.status not in ("Newton_Succeeded", "Barrier_Succeeded")
    assert sb.status == "Barrier_Succeeded" and sb.success and sb.iterations <= 30
    assert sb.slack > 0  # the violated bound is relaxed by its slack
    np.testing.assert_allclose(sb.action, sa.action, rtol=0, atol=1e-5)
    np.testing.assert_allclose(sb.value, sa.value, rtol=1e-7)
    np.testing.assert_allclose(sb.slack, sa.slack, rtol=1e-6)
    scale = np.abs(sa.dpi_dtheta).max(axis=0)
    assert np.all(np.abs(sb.dpi_dtheta - sa.dpi_dtheta) <= 1e-4 * scale)
    np.testing.assert_allclose(sb.dV_dtheta, sa.dV_dtheta, rtol=1e-4, atol=1e-6)


def test_closed_loop_with_the_barrier_path_is_ipopts(cstr, pair):
    # a start from the benchmark's states whose first warm steps violate a bound
    ipopt, mpc = pair
    x = np.array([88.0, 0.2, 455.0])
    for m in pair:
        m.reset()
    used = 0
    for _ in range(8):
        sa, sb = ipopt.solve(x, ipopt.theta0), mpc.solve(x, mpc.theta0)
        assert sa.success and sb.success
        used += sb.status == "Barrier_Succeeded"
        np.testing.assert_allclose(sb.action, sa.action, rtol=0, atol=1e-5)
        np.testing.assert_allclose(sb.value, sa.value, rtol=1e-7)
        x = cstr.plant_step(x, sa.action)
    assert used >= 2


def test_barrier_sensitivities_match_central_differences(cstr):
    mpc = ParametricMPC(cstr, barrier_steps=30)
    th = mpc.theta0.copy()
    _warm(cstr, mpc, th)
    assert_warm_sensitivities_match_fd(mpc, X_VIOLATING[0], th, "Barrier_Succeeded")


def test_a_saddle_point_goes_to_ipopt(cstr, pair):
    # the second-order check rejects the barrier path's point: IPOPT solves, same answer
    ipopt, mpc = pair
    x = X_VIOLATING[0]
    for m in pair:
        _warm(cstr, m, m.theta0)
    checked = []
    mpc._is_local_minimum = lambda y, p: checked.append(1) and False
    try:
        sb = mpc.solve(x, mpc.theta0)
    finally:
        del mpc._is_local_minimum
    sa = ipopt.solve(x, ipopt.theta0)
    assert checked and sb.success and sb.status == sa.status
    np.testing.assert_allclose(sb.action, sa.action, rtol=0, atol=1e-7)


def _ipopt_primal_dual(mpc):
    """The parameters at the calm state and IPOPT's primal-dual solution y = (w, lam, mu)."""
    p = np.concatenate([X_CALM, mpc.theta0])
    ok, _, _, out, w = mpc._run_solver(X_CALM, p, False)
    assert ok
    lam, mu = mpc._multipliers(
        w, np.asarray(out["lam_g"]).ravel(), np.asarray(out["lam_x"]).ravel()
    )
    return p, np.concatenate([w, lam, mu])


def test_the_local_minimum_check(cstr, pair):
    # at IPOPT's barrier solution the barrier Hessian is positive definite on the null space
    # of the equality constraints; with the curvature of the cost reversed it is not
    ipopt, mpc = pair
    p, y = _ipopt_primal_dual(mpc)
    assert mpc._is_local_minimum(y, p)
    th = mpc.theta0.copy()
    for block in ("Q", "R", "T"):
        th[mpc.param.blocks[block]] *= -1.0
    assert not mpc._is_local_minimum(y, np.concatenate([X_CALM, th]))


def test_barrier_options_are_checked(cstr):
    with pytest.raises(ValueError, match="barrier_steps must be an integer >= 0, got -1"):
        ParametricMPC(cstr, barrier_steps=-1)
    with pytest.raises(ValueError, match=r"barrier_mu0 must be in \(0, 1\), got 2"):
        ParametricMPC(cstr, barrier_mu0=2)


def test_runs_saved_before_the_setting_resume_without_it(tmp_path):
    # a run whose config.toml has no barrier_steps was made without the barrier path
    new = Settings(mpc={"barrier_steps": 30})
    assert Settings().mpc.barrier_steps == 0 and new.mpc.options()["barrier_steps"] == 30
    text = settings_to_toml(new)
    (tmp_path / "config.toml").write_text(text)
    assert RunDirectory(tmp_path).saved_settings().mpc.barrier_steps == 30
    old = "\n".join(
        line
        for line in text.splitlines()
        if not line.startswith(("barrier_steps", "barrier_mu0", "barrier_push"))
    )
    (tmp_path / "config.toml").write_text(old)
    assert RunDirectory(tmp_path).saved_settings().mpc.barrier_steps == 0


def test_barrier_push_setting_reaches_the_mpc(cstr):
    # [mpc] barrier_push (default true: the behaviour before the option) is passed to the MPC
    assert Settings().mpc.barrier_push is True
    options = Settings(mpc={"barrier_steps": 30, "barrier_push": False}).mpc.options()
    mpc = ParametricMPC(cstr, **{k: v for k, v in options.items() if k != "codegen"})
    assert mpc._barrier_push is False
    assert ParametricMPC(cstr, barrier_steps=30)._barrier_push is True


def test_the_reduced_hessian_is_the_barrier_hessian_on_the_null_space(cstr, pair):
    # M = Z^T K Z for a basis Z of the null space of the equality Jacobian A (A Z = 0), at a
    # minimum and at a saddle (the curvature of the cost reversed)
    ipopt, mpc = pair
    nw, neq = mpc.nw, mpc.neq
    p, y = _ipopt_primal_dual(mpc)
    th = mpc.theta0.copy()
    for block in ("Q", "R", "T"):
        th[mpc.param.blocks[block]] *= -1.0
    for theta, minimum in ((mpc.theta0, True), (th, False)):
        pt = np.concatenate([X_CALM, theta])
        Kxx, Kxr, Krr, Ax, Ar = mpc._soc_call(y[:nw], y[nw : nw + neq], y[nw + neq :], pt)
        K = np.block([[Kxx, Kxr], [Kxr.T, Krr]])
        A = np.hstack([Ax, Ar])
        Z = np.vstack([-np.linalg.solve(Ax, Ar), np.eye(Ar.shape[1])])
        np.testing.assert_allclose(A @ Z, 0.0, atol=1e-9 * np.abs(A).max())
        M = mpc._reduced_hessian(y, pt)
        # compared entry by entry at the scale of their diagonal (which spans 1 to 1e11)
        d = np.sqrt(np.abs(np.diag(M)))
        np.testing.assert_allclose((M - Z.T @ K @ Z) / np.outer(d, d), 0.0, atol=1e-9)
        assert mpc._is_local_minimum(y, pt) == minimum


def test_barrier_path_from_interior_starts_only(cstr, pair):
    # barrier_push=False: a violated row sends the solve to IPOPT without a barrier attempt;
    # from the interior warm starts of the benchmark's first episode (the Newton steps at tau
    # converge too slowly there) the path gives IPOPT's solution and sensitivities
    ipopt, _ = pair
    mpc = ParametricMPC(cstr, barrier_steps=30, barrier_push=False)
    calls = []
    call = mpc._barrier_call
    mpc._barrier_call = lambda *a: calls.append(1) or call(*a)
    try:
        _warm(cstr, mpc, mpc.theta0)
        calls.clear()
        sol = mpc.solve(X_VIOLATING[0], mpc.theta0)
        assert sol.success and sol.status not in ("Newton_Succeeded", "Barrier_Succeeded")
        assert not calls
    finally:
        mpc._barrier_call = call
    x = cstr.sample_initial_state(np.random.default_rng(0))
    for m in (ipopt, mpc):
        m.reset()
    used = 0
    for _ in range(5):
        sa, sb = ipopt.solve(x, ipopt.theta0), mpc.solve(x, mpc.theta0)
        assert sa.success and sb.success
        used += sb.status == "Barrier_Succeeded"
        np.testing.assert_allclose(sb.action, sa.action, rtol=0, atol=1e-5)
        scale = np.abs(sa.dpi_dtheta).max(axis=0)
        assert np.all(np.abs(sb.dpi_dtheta - sa.dpi_dtheta) <= 1e-4 * scale)
        np.testing.assert_allclose(sb.dV_dtheta, sa.dV_dtheta, rtol=1e-4, atol=1e-6)
        x = cstr.plant_step(x, sa.action)
    assert used >= 2
