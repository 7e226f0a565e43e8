"""Wall time of one closed-loop MPC step (solve + both sensitivities) on the CSTR.

For every state of a few 60-step closed-loop CSTR episodes, this times

* each variant of our :class:`mpcmobo.mpc.ParametricMPC` (``mpc.solve(x, theta0,
  sensitivities=True)``: the solve, dpi/dtheta and dV/dtheta), and
* the BASELINE built in the same run, the reference of every ratio: the same MPC (horizon N,
  gamma, the cost of section 5 at theta0, l1 slacks with Gamma = 1e5 on the state bounds, input
  bounds, the RK4 model of the imperfect plant, physical unscaled variables) written as a CasADi
  expert would: ``casadi.Opti`` with its functions expanded to SX (``"expand": True``), called
  through ``Opti.to_function``, IPOPT with the tolerances of our MPC (``tol``, ``acceptable_tol``)
  and otherwise its defaults. The solve call alone is timed, no sensitivities. Its initial
  guess is the previous step's primal solution (unshifted); at the first step of an episode,
  the current state for every predicted state and ``u_ref`` for every input, zero slacks.
* ``baseline_mx``, an extra row: the same ``Opti`` problem with MX function graphs, called
  through ``opti.solve()`` (the baseline of issue 2, which made the ratios look 4-5x larger).

The measurements of all variants and the baseline are interleaved state by state (the order
rotates each step), so load from other processes on the shared machine hits them alike. The
plant is stepped with the first variant's action, so every solver sees the same states.
Reported: median and 95th percentile per row; ``ratio`` = baseline median / variant median
(on a baseline row: that baseline's median / the first variant's median), ``ratio_mx`` the
same against ``baseline_mx``.

    .venv/bin/python benchmarks/step_time.py            # 4 episodes x 60 steps
    .venv/bin/python benchmarks/step_time.py --quick    # 1 episode x 20 steps
"""

from __future__ import annotations

import argparse
import inspect
import json
import platform
import time

import casadi as ca
import numpy as np

from mpcmobo.mpc import ParametricMPC
from mpcmobo.systems import get_system
from mpcmobo.systems.base import rk4_step

# the IPOPT tolerances of our MPC (ParametricMPC's default tol; acceptable_tol as it derives it)
TOL = inspect.signature(ParametricMPC).parameters["tol"].default
ACCEPTABLE_TOL = max(1e-6, 100 * TOL)


class OptiBaseline:
    """The same MPC as a plain ``casadi.Opti`` problem in physical units.

    ``expand=True``: the NLP functions are expanded to SX (``opti.solver("ipopt", {"expand":
    True})``) and the solve is one call of ``opti.to_function`` (what a CasADi expert writes; the
    reference). ``expand=False``: MX function graphs, called through ``opti.solve()`` (the
    baseline of issue 2, kept as an extra row). IPOPT: the tolerances of our MPC (``tol`` 1e-8,
    ``acceptable_tol`` 1e-6, which are also IPOPT's defaults), otherwise IPOPT's defaults.
    """

    def __init__(self, s, model: str = "imperfect", warm: bool = True, expand: bool = True) -> None:
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
        opti.solver(
            "ipopt",
            {"print_time": False, "show_eval_warnings": False, "expand": expand},
            {"print_level": 0, "sb": "yes", "tol": TOL, "acceptable_tol": ACCEPTABLE_TOL},
        )
        self.opti, self.X, self.U, self.E, self.x0 = opti, X, U, E, x0
        self.expand = expand
        # expanded: x0 and the initial guess in, the solution out, one Function call
        self._fn = opti.to_function("baseline", [x0, X, U, E], [X, U, E]) if expand else None
        self._prev = None

    def reset(self) -> None:
        self._prev = None

    def solve(self, x):
        """Returns (wall time of the solve call, success, iterations, first input)."""
        if self.expand:
            return self._solve_function(x)
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

    def _solve_function(self, x):
        if self.warm and self._prev is not None:
            guess = self._prev  # the previous step's primal solution, unshifted
        else:
            guess = (
                np.tile(x[:, None], (1, self.N + 1)),
                np.tile(self.s.u_ref[:, None], (1, self.N)),
                np.zeros((self.s.nx, self.N + 1)),
            )
        t0 = time.perf_counter()
        try:
            out = self._fn(x, *guess)
            raised = False
        except RuntimeError:
            raised = True
        dt = time.perf_counter() - t0
        stats = self._fn.stats()
        ok = not raised and bool(stats.get("success", False))
        self._prev = tuple(np.asarray(o) for o in out) if ok else None
        u0 = self._prev[1][:, 0].copy() if ok else None
        return dt, ok, int(stats.get("iter_count", 0)), u0


# name -> ParametricMPC options; the first one drives the closed loop.
VARIANTS: dict[str, dict] = {
    "default": {},  # IPOPT, shifted primal-dual warm start, adjoint sensitivities (sparse QR)
    "cold": {"warm_start": False},  # no warm start
    "warm_mu_init_1e-5": {"warm_options": {"mu_init": 1e-5}},
    "warm_mu_adaptive": {"warm_options": {"mu_strategy": "adaptive"}},
    "jit": {"jit": True},  # generated, compiled C for the NLP and KKT functions
}


# name -> OptiBaseline options; "baseline" is the reference of every ratio.
BASELINES: dict[str, dict] = {
    "baseline": {"expand": True},  # SX, Opti.to_function, warm: the expert's formulation
    "baseline_mx": {"expand": False},  # MX, opti.solve(), warm: the baseline of issue 2
}
_BASELINE_LABELS = {
    "baseline": "Opti, expand=True (SX), Opti.to_function, our tolerances",
    "baseline_mx": "Opti, MX, opti.solve(), our tolerances (the issue-2 baseline)",
}


def run(episodes: int, steps: int, variants: dict[str, dict], seed: int = 0) -> dict:
    s = get_system("cstr")
    mpcs = {name: ParametricMPC(s, "imperfect", **opts) for name, opts in variants.items()}
    bases = {name: OptiBaseline(s, **opts) for name, opts in BASELINES.items()}
    names = [*mpcs, *bases]
    times = {n: [] for n in names}
    iters = {n: [] for n in names}
    fails = {n: 0 for n in names}
    du = {n: [] for n in mpcs}  # |action - baseline action|, a sanity check of "same problem"
    rng = np.random.default_rng(seed)
    x0s = [s.sample_initial_state(rng) for _ in range(episodes)]
    theta0 = next(iter(mpcs.values())).theta0
    first = names[0]
    # one untimed solve per variant and baseline (first-call allocations)
    for m in mpcs.values():
        m.solve(x0s[0], theta0, sensitivities=True)
        m.reset()
    for b in bases.values():
        b.solve(x0s[0])
        b.reset()
    for x0 in x0s:
        for m in mpcs.values():
            m.reset()
        for b in bases.values():
            b.reset()
        x = x0.copy()
        for k in range(steps):
            order = names[k % len(names) :] + names[: k % len(names)]
            actions = {}
            for n in order:
                if n in bases:
                    dt, ok, it, u0 = bases[n].solve(x)
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
    med = {n: float(np.median(times[n])) for n in names}
    res = {}
    for n in names:
        t = np.array(times[n]) * 1e3
        if n in bases:  # this baseline's solve / our first variant's step
            ratio = {"ratio": med[n] / med[first]}
        else:  # a baseline's solve / this variant's step
            ratio = {"ratio": med["baseline"] / med[n], "ratio_mx": med["baseline_mx"] / med[n]}
        res[n] = {
            "median_ms": float(np.median(t)),
            "p95_ms": float(np.percentile(t, 95)),
            "mean_iters": float(np.mean(iters[n])),
            "failures": int(fails[n]),
            **ratio,
            "max_du_vs_baseline": float(np.max(du[n])) if n in du and du[n] else None,
            "variant": variants.get(n, _BASELINE_LABELS.get(n)),
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
    first = next(iter(variants))
    print(
        f"ratio: baseline median / variant median; on a baseline row: that baseline's median / "
        f"{first!r} median. ratio_mx: the same against baseline_mx"
    )
    hdr = (
        f"{'variant':<22} {'median ms':>10} {'p95 ms':>8} {'iters':>6} {'fail':>5} "
        f"{'ratio':>6} {'ratio_mx':>8}"
    )
    print(hdr)
    for n, r in res.items():
        rmx = f"{r['ratio_mx']:>8.2f}" if "ratio_mx" in r else f"{'':>8}"
        print(
            f"{n:<22} {r['median_ms']:>10.2f} {r['p95_ms']:>8.2f} {r['mean_iters']:>6.1f} "
            f"{r['failures']:>5d} {r['ratio']:>6.2f} {rmx}"
        )
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=2, default=str)


if __name__ == "__main__":
    main()
