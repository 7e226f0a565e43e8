"""Probe: fatrop (CasADi's structure-exploiting interior-point solver) on the CSTR MPC.

The same NLP as :class:`mpcmobo.mpc.ParametricMPC` builds (scaled variables, l1 slacks, input and
slack bounds), reordered stage by stage for fatrop (``structure_detection="manual"``: stage k has
the state x_k and the controls (u_k, eta_k); the gap rows ``z_{k+1} - (F(x_k, u_k) - x_r) / S_x``
first, then the stage's inequalities), solved along the closed loop of our default MPC with the
previous fatrop solution (primal only: fatrop 1.1.8 in CasADi 3.8.2 has no option for warm
multipliers) as the initial guess. It prints, per step, fatrop's and IPOPT's (our default, no
sensitivities) wall time and |u_fatrop - u_ours|.

What it shows: fatrop's own barrier goes to 0 (it has no ``mu_target``), so its solution is not
the barrier solution at tau that our policy and its exact sensitivities are defined by; it is
measured here as the speed a structure-exploiting solver reaches, not used by the package.

    PYTHONPATH=src .venv/bin/python benchmarks/fatrop_probe.py [--episodes 2]
"""

from __future__ import annotations

import argparse
import time

import casadi as ca
import numpy as np

from mpcmobo.mpc import ParametricMPC
from mpcmobo.systems import get_system


class FatropMPC:
    """The NLP of ``mpc`` (at theta), stage-wise, solved by fatrop."""

    def __init__(self, mpc: ParametricMPC, tol: float = 1e-8) -> None:
        N, nx = mpc.N, mpc.nx
        x0, th = ca.SX.sym("x0", nx), ca.SX.sym("th", mpc.n_theta)
        wv, geq, gin, f = mpc._transcribe(x0, th)
        X0 = ca.SX.sym("X0", nx)  # the initial state as fatrop's stage-0 state variable
        sub = lambda e: ca.substitute(e, x0, X0)  # noqa: E731
        geq, gin, f = sub(geq), sub(gin), sub(f)
        m = gin.numel() // (N + 1)
        self.ctrl = [(list(mpc._iu[k]) if k < N else []) + list(mpc._ie[k]) for k in range(N + 1)]
        parts, g, lbg, ubg = [], [], [], []
        for k in range(N + 1):
            parts.append(X0 if k == 0 else wv[list(mpc._ix[k - 1])])
            parts.append(wv[self.ctrl[k]])
            if k < N:  # gap-closing rows: x_{k+1} - F(x_k, u_k), scaled
                g.append(-geq[k * nx : (k + 1) * nx])
                lbg += [0.0] * nx
                ubg += [0.0] * nx
            if k == 0:
                g.append(X0 - x0)
                lbg += [0.0] * nx
                ubg += [0.0] * nx
            g.append(gin[k * m : (k + 1) * m])
            lbg += [-np.inf] * m
            ubg += [0.0] * m
        nlp = {"x": ca.vertcat(*parts), "p": ca.vertcat(x0, th), "f": f, "g": ca.vertcat(*g)}
        opts = {
            "structure_detection": "manual",
            "N": N,
            "nx": [nx] * (N + 1),
            "nu": [len(c) for c in self.ctrl],
            "ng": [nx + m] + [m] * N,
            "expand": True,
            "print_time": False,
            "show_eval_warnings": False,
            "fatrop": {"print_level": 0, "tol": tol, "max_iter": 150},
        }
        self.solver = ca.nlpsol("fatrop_mpc", "fatrop", nlp, opts)
        self.mpc, self.lbg, self.ubg = mpc, lbg, ubg
        self.lbx = self._to_z(mpc._lbw, np.full(nx, -np.inf))
        self.ubx = self._to_z(mpc._ubw, np.full(nx, np.inf))
        self.prev = None

    def _to_z(self, w, x):
        mpc = self.mpc
        out = [np.asarray(x, float)]
        for k in range(mpc.N + 1):
            if k > 0:
                out.append(w[mpc._ix[k - 1]])
            out.append(w[self.ctrl[k]])
        return np.concatenate(out)

    def _to_w(self, z):
        mpc, nx = self.mpc, self.mpc.nx
        w, pos = np.zeros(mpc.nw), nx
        for k in range(mpc.N + 1):
            if k > 0:
                w[mpc._ix[k - 1]] = z[pos : pos + nx]
                pos += nx
            w[self.ctrl[k]] = z[pos : pos + len(self.ctrl[k])]
            pos += len(self.ctrl[k])
        return w

    def solve(self, x, theta):
        """(wall time, success, iterations, first input)."""
        z0 = self._to_z(self.prev if self.prev is not None else self.mpc._cold_guess(x), x)
        args = dict(x0=z0, p=np.concatenate([x, theta]), lbg=self.lbg, ubg=self.ubg)
        t0 = time.perf_counter()
        out = self.solver(lbx=self.lbx, ubx=self.ubx, **args)
        dt = time.perf_counter() - t0
        st = self.solver.stats()
        w = self._to_w(np.asarray(out["x"]).reshape(-1))
        ok = bool(st["success"])
        self.prev = w if ok else None
        mpc = self.mpc
        u0 = mpc.system.u_ref + mpc.Su * w[mpc._iu[0]]
        return dt, ok, int(st["iter_count"]), u0


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--episodes", type=int, default=2)
    ap.add_argument("--steps", type=int, default=60)
    args = ap.parse_args(argv)
    s = get_system("cstr")
    ours = ParametricMPC(s, "imperfect", newton_steps=0)  # IPOPT at tau, our default options
    fat = FatropMPC(ParametricMPC(s, "imperfect"))
    rng = np.random.default_rng(0)
    t_ours, t_fat, it_ours, it_fat, du, fails = [], [], [], [], [], 0
    for _ in range(args.episodes):
        x = s.sample_initial_state(rng)
        ours.reset()
        fat.prev = None
        for _ in range(args.steps):
            t0 = time.perf_counter()
            sol = ours.solve(x, ours.theta0, sensitivities=False)
            t_ours.append(time.perf_counter() - t0)
            dt, ok, it, u0 = fat.solve(x, ours.theta0)
            t_fat.append(dt)
            it_ours.append(sol.iterations)
            it_fat.append(it)
            fails += not ok
            if ok and sol.success:
                du.append(float(np.max(np.abs(u0 - sol.action))))
            x = s.plant_step(x, sol.action)
    print(f"CSTR, {args.episodes} episode(s) x {args.steps} steps, casadi {ca.__version__}")
    print(
        f"IPOPT (ours, at tau, no sensitivities): median {1e3 * np.median(t_ours):.2f} ms, "
        f"mean iterations {np.mean(it_ours):.1f}"
    )
    print(
        f"fatrop (barrier to 0):                  median {1e3 * np.median(t_fat):.2f} ms, "
        f"mean iterations {np.mean(it_fat):.1f}, failures {fails}"
    )
    print(f"ratio IPOPT / fatrop (medians): {np.median(t_ours) / np.median(t_fat):.2f}")
    print(f"|u_fatrop - u_ours|: median {np.median(du):.1e}, max {np.max(du):.1e}")


if __name__ == "__main__":
    main()
