"""Wall time of one closed-loop MPC step (solve + both sensitivities) on the CSTR.

For every state of a few 60-step closed-loop CSTR episodes, this times

* each variant of our :class:`mpcmobo.mpc.ParametricMPC` (``mpc.solve(x, theta0,
  sensitivities=True)``: the solve, dpi/dtheta and dV/dtheta), and
* a BASELINE built in the same run: a plain CasADi ``Opti`` + IPOPT formulation of the same
  MPC (horizon N, gamma, the cost of section 5 at theta0, l1 slacks with Gamma = 1e5 on the
  state bounds, input bounds, the RK4 model of the imperfect plant, physical unscaled
  variables, default IPOPT options except ``print_level 0``). ``opti.solve()`` alone is timed,
  no sensitivities. Its initial guess is the previous step's primal solution (unshifted) via
  ``opti.set_initial``; at the first step of an episode, the current state for every predicted
  state and ``u_ref`` for every input.

The measurements of all variants and the baseline are interleaved state by state (the order
rotates each step), so load from other processes on the shared machine hits them alike. The
plant is stepped with the first variant's action, so every solver sees the same states.
Reported: median and 95th percentile per variant, and the ratio baseline median / ours median.

    .venv/bin/python benchmarks/step_time.py            # 4 episodes x 60 steps
    .venv/bin/python benchmarks/step_time.py --quick    # 1 episode x 20 steps
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import casadi as ca
import numpy as np

from mpcmobo.mpc import ParametricMPC
from mpcmobo.systems import get_system
from mpcmobo.systems.base import rk4_step


class OptiBaseline:
    """The same MPC as a plain ``casadi.Opti`` problem in physical units, default IPOPT."""

    def __init__(self, s, model: str = "imperfect", warm: bool = True) -> None:
        mpc_spec = s.mpc_spec
        N, gamma = mpc_spec.horizon, mpc_spec.gamma
        nx, nu = s.nx, s.nu
        Gamma = np.full(nx, 1e5) if mpc_spec.Gamma is None else np.asarray(mpc_spec.Gamma)
        Gamma_f = Gamma if mpc_spec.Gamma_f is None else np.asarray(mpc_spec.Gamma_f)
        pm = s.model_params(model)
        th = s.parameterization.theta0  # the cost weights of section 5
        b = s.parameterization.blocks
        Tw, G, Qw, Rw = th[b["T"]], th[b["G"]], th[b["Q"]], th[b["R"]]
        theta_c = th[b["theta_c"]][0]
        self.N, self.s, self.warm = N, s, warm

        opti = ca.Opti()
        X = opti.variable(nx, N + 1)
        U = opti.variable(nu, N)
        E = opti.variable(nx, N + 1)
        x0 = opti.parameter(nx)
        xr, ur = ca.DM(s.x_ref), ca.DM(s.u_ref)
        opti.subject_to(X[:, 0] == x0)
        cost = theta_c
        for i in range(N + 1):
            dx = X[:, i] - xr
            opti.subject_to(E[:, i] >= 0)
            opti.subject_to(X[:, i] >= ca.DM(s.x_lb) - E[:, i])
            opti.subject_to(X[:, i] <= ca.DM(s.x_ub) + E[:, i])
            if i < N:
                du = U[:, i] - ur
                opti.subject_to(opti.bounded(ca.DM(s.u_lb), U[:, i], ca.DM(s.u_ub)))
                xn = rk4_step(s.dynamics, X[:, i], U[:, i], ca.DM(pm), s.dt, s.substeps)
                opti.subject_to(X[:, i + 1] == xn)
                cost += gamma**i * (
                    ca.dot(dx, Qw * dx) + ca.dot(du, Rw * du) + ca.dot(ca.DM(Gamma), E[:, i])
                )
                cost += ca.dot(ca.DM(G), ca.vertcat(dx, du))
            else:
                cost += ca.dot(ca.DM(G[:nx]), dx)
                cost += gamma**N * (ca.dot(dx, Tw * dx) + ca.dot(ca.DM(Gamma_f), E[:, i]))
        opti.minimize(cost)
        opti.solver("ipopt", {"print_time": False}, {"print_level": 0})
        self.opti, self.X, self.U, self.E, self.x0 = opti, X, U, E, x0
        self._prev = None

    def reset(self) -> None:
        self._prev = None

    def solve(self, x):
        """Returns (wall time of opti.solve(), success, iterations, first input)."""
        opti = self.opti
        opti.set_value(self.x0, x)
        if self.warm and self._prev is not None:
            opti.set_initial(self._prev)
        else:
            opti.set_initial(self.X, np.tile(x[:, None], (1, self.N + 1)))
            opti.set_initial(self.U, np.tile(self.s.u_ref[:, None], (1, self.N)))
            opti.set_initial(self.E, 0.0)
        t0 = time.perf_counter()
        try:
            sol = opti.solve()
            ok = True
        except RuntimeError:
            sol, ok = opti.debug, False
        dt = time.perf_counter() - t0
        stats = opti.stats()
        if ok:
            self._prev = sol.value_variables()
        else:
            self._prev = None
        u0 = np.asarray(sol.value(self.U[:, 0])).reshape(-1) if ok else None
        return dt, ok, int(stats.get("iter_count", 0)), u0


# name -> ParametricMPC options; the first one drives the closed loop.
VARIANTS: dict[str, dict] = {
    "default": {},  # IPOPT, shifted primal-dual warm start, adjoint sensitivities (sparse QR)
    "cold": {"warm_start": False},  # no warm start
    "warm_mu_init_1e-5": {"warm_options": {"mu_init": 1e-5}},
    "warm_mu_adaptive": {"warm_options": {"mu_strategy": "adaptive"}},
    "jit": {"jit": True},  # generated, compiled C for the NLP and KKT functions
}


def run(episodes: int, steps: int, variants: dict[str, dict], seed: int = 0) -> dict:
    s = get_system("cstr")
    mpcs = {name: ParametricMPC(s, "imperfect", **opts) for name, opts in variants.items()}
    base = OptiBaseline(s)
    names = [*mpcs, "baseline"]
    times = {n: [] for n in names}
    iters = {n: [] for n in names}
    fails = {n: 0 for n in names}
    du = {n: [] for n in mpcs}  # |action - baseline action|, a sanity check of "same problem"
    rng = np.random.default_rng(seed)
    x0s = [s.sample_initial_state(rng) for _ in range(episodes)]
    theta0 = next(iter(mpcs.values())).theta0
    first = names[0]
    # one untimed solve per variant (first-call allocations)
    for m in mpcs.values():
        m.solve(x0s[0], theta0, sensitivities=True)
        m.reset()
    base.solve(x0s[0])
    base.reset()
    for x0 in x0s:
        for m in mpcs.values():
            m.reset()
        base.reset()
        x = x0.copy()
        for k in range(steps):
            order = names[k % len(names) :] + names[: k % len(names)]
            actions = {}
            for n in order:
                if n == "baseline":
                    dt, ok, it, u0 = base.solve(x)
                    actions[n] = u0
                else:
                    t0 = time.perf_counter()
                    sol = mpcs[n].solve(x, theta0, sensitivities=True)
                    dt = time.perf_counter() - t0
                    ok, it = sol.success, sol.iterations
                    actions[n] = sol.action
                    ok = ok and bool(np.all(np.isfinite(sol.dpi_dtheta)))
                times[n].append(dt)
                iters[n].append(it)
                fails[n] += not ok
            if actions["baseline"] is not None:
                for n in mpcs:
                    du[n].append(float(np.max(np.abs(actions[n] - actions["baseline"]))))
            x = s.plant_step(x, actions[first])
    res = {}
    tb = np.array(times["baseline"]) * 1e3
    for n in names:
        t = np.array(times[n]) * 1e3
        res[n] = {
            "median_ms": float(np.median(t)),
            "p95_ms": float(np.percentile(t, 95)),
            "mean_iters": float(np.mean(iters[n])),
            "failures": int(fails[n]),
            "ratio": float(np.median(tb) / np.median(t)),
            "max_du_vs_baseline": float(np.max(du[n])) if n in du and du[n] else None,
            "variant": variants.get(n, "Opti + IPOPT defaults"),
        }
    return res


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1 episode of 20 steps")
    ap.add_argument("--episodes", type=int, default=4)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--variants", nargs="*", default=None, help=f"subset of {list(VARIANTS)} (default: all)"
    )
    ap.add_argument("--json", default=None, help="write the results to this file")
    args = ap.parse_args(argv)
    episodes, steps = (1, 20) if args.quick else (args.episodes, args.steps)
    variants = VARIANTS if not args.variants else {k: VARIANTS[k] for k in args.variants}
    res = run(episodes, steps, variants, args.seed)
    print(
        f"CSTR, {episodes} episode(s) x {steps} steps, casadi {ca.__version__}, "
        f"{platform.machine()}, python {platform.python_version()}"
    )
    hdr = f"{'variant':<22} {'median ms':>10} {'p95 ms':>8} {'iters':>6} {'fail':>5} {'ratio':>6}"
    print(hdr)
    for n, r in res.items():
        print(
            f"{n:<22} {r['median_ms']:>10.2f} {r['p95_ms']:>8.2f} {r['mean_iters']:>6.1f} "
            f"{r['failures']:>5d} {r['ratio']:>6.2f}"
        )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=2, default=str)


if __name__ == "__main__":
    main()
