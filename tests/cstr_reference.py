"""Independent references for the tests: the CSTR of the paper written out in numpy (no CasADi),
and central finite differences of an MPC's policy and value in theta."""

from __future__ import annotations

import math

import numpy as np


def paper_rhs(x, u, mult=(1, 1, 1, 1, 1)):
    """eq. (CSTR_model) / (CSTR_Wrongmodel) written out with Table 1, independently of casadi."""
    V, Ca, T = x
    qs, qc = u
    qo, Cao, To, Tco = 100.0, 1.0, 350.0, 350.0
    dH, rhoCp, k0, ER, rhocCpc, hA = -2e5, 1000.0, 7.2e10, 1e4, 1000.0, 7e5
    k1, k2, k3 = -dH * k0 / rhoCp, rhocCpc / rhoCp, hA / rhocCpc
    r = math.exp(-ER / T)
    return np.array(
        [
            qo - qs,
            mult[0] * qo / V * (Cao - Ca) - mult[1] * k0 * r * Ca,
            qo / V * (To - T)
            + mult[2] * k1 * r * Ca
            + mult[3] * k2 * qc / V * (1 - math.exp(-mult[4] * k3 / qc)) * (Tco - T),
        ]
    )


def hand_rk4(x, u, mult=(1, 1, 1, 1, 1), dt=0.05):
    """One classical RK4 step of :func:`paper_rhs` (dt = 0.05 min, Table 1)."""
    k1 = paper_rhs(x, u, mult)
    k2 = paper_rhs(x + dt / 2 * k1, u, mult)
    k3 = paper_rhs(x + dt / 2 * k2, u, mult)
    k4 = paper_rhs(x + dt * k3, u, mult)
    return x + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def fd_sensitivities(mpc, x, theta, rel_step=1e-5, solve=None):
    """Central differences of the MPC's first input and value in each theta coordinate (step
    ``rel_step * max(1, |theta_i|)``), solved without sensitivities: (dpi (n_theta, nu), dV).
    ``solve(theta, sensitivities)``, if given, replaces ``mpc.solve(x, ...)`` (e.g. to restore a
    warm start before each solve)."""
    if solve is None:

        def solve(th, sens):
            return mpc.solve(x, th, sens)

    theta = np.asarray(theta, dtype=float)
    dpi = np.zeros((theta.size, mpc.system.nu))
    dV = np.zeros(theta.size)
    for i in range(theta.size):
        h = rel_step * max(1.0, abs(theta[i]))
        tp, tm = theta.copy(), theta.copy()
        tp[i] += h
        tm[i] -= h
        sp, sm = solve(tp, False), solve(tm, False)
        dpi[i] = (sp.action - sm.action) / (2 * h)
        dV[i] = (sp.value - sm.value) / (2 * h)
    return dpi, dV


def assert_warm_sensitivities_match_fd(mpc, x, theta, status):
    """The MPC's exact sensitivities at ``x`` against :func:`fd_sensitivities`, every solve
    warm-started from the MPC's current warm start (restored before each one) and ending with
    ``status`` (the solver path under test)."""
    prev = {k: (v.copy() if isinstance(v, np.ndarray) else v) for k, v in mpc.solver.prev.items()}

    def solve(th, sens):
        mpc.solver.prev = dict(prev)
        sol = mpc.solve(x, th, sens)
        assert sol.status == status
        return sol

    sol = solve(theta, True)
    dpi, dV = fd_sensitivities(mpc, x, theta, solve=solve)
    # an input at its bound has sensitivities ~1e-7, at the level of the differences' noise
    tol_pi = 1e-4 * np.abs(dpi).max(axis=0) + 1e-6 * np.abs(dpi).max()
    assert np.all(np.abs(sol.dpi_dtheta - dpi) <= tol_pi)
    assert np.all(np.abs(sol.dV_dtheta - dV) <= 1e-4 * np.abs(dV) + 1e-6 * np.abs(dV).max())
