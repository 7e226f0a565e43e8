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
* ``fatrop``, the second reference (``ratio_fat``): the same MPC as an expert's fatrop NMPC
  (:class:`FatropBaseline`: stage-wise ``Opti``, structure detection, jit-compiled functions,
  warm-started from the previous primal solution).
* ``baseline_mx``, an extra row: the same ``Opti`` problem with MX function graphs, called
  through ``opti.solve()`` (MX graphs evaluate more slowly than SX: against it every ratio
  looks 4-5x larger).
* ``mpcrl``, a peer row (``pip install 'mpcmobo[bench]'``, skipped without it): the same MPC
  in ``mpcrl`` 1.4.1 driven by its ``LstdDpgAgent`` (:class:`MpcrlPeer`): its solve plus its
  dpi/dtheta per step.

For our variants the step is split into components: the solver (Newton steps, the
interior-point continuation and IPOPT calls; of the IPOPT calls, IPOPT's own function-evaluation
time from its statistics), the two
sensitivities, and the rest (Python); ``build_s`` is the construction time of the MPC (with
``codegen``, the first build in a run compiles into an empty cache directory, the second one
loads the library: set ``MPCMOBO_CACHE_DIR`` to a new directory to see both).
``du_first`` is the largest |action - the first variant's action| over all steps: the same
policy gives about 1e-7, a different local solution in the constraint-violating phases tens.
``du_ipopt`` compares with the ``ipopt`` variant (IPOPT alone on the same barrier problem, so
the same policy; the baselines solve the problem without the barrier, about 1e-4 away).
``paths`` counts the steps solved by the Newton steps, the continuation from the warm start, the
one restarted from the shifted plan, the continuation from the cold guess and IPOPT.

The measurements of all variants and the baseline are interleaved state by state (in a new
random order each step), so load from other processes on the shared machine hits them alike. The
plant is stepped with the first variant's action, so every solver sees the same states.
Reported: median and 95th percentile per row; ``ratio`` = baseline median / variant median
(on a baseline row: that baseline's median / the first variant's median), ``ratio_mx`` the
same against ``baseline_mx``.

    .venv/bin/python benchmarks/step_time.py            # 4 episodes x 60 steps
    .venv/bin/python benchmarks/step_time.py --quick    # 1 episode x 20 steps
    .venv/bin/python benchmarks/step_time.py --variants codegen default ipopt codegen_no_continuation --no-peers
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
    reference). ``expand=False``: MX function graphs, called through ``opti.solve()`` (an extra
    row). IPOPT: the tolerances of our MPC (``tol`` 1e-8,
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
        previous = self._prev if self.warm else None  # the last primal solution, unshifted
        dt, ok, iters, self._prev, u0 = solve_warm(self._fn, x, previous, self.s, self.N)
        return dt, ok, iters, u0


def solve_warm(fn, x, previous, s, N):
    """One call of an expert's solver function ``fn(x, X, U, eta)`` from ``previous`` (its
    last primal solution), else the cold guess (x held, u_ref, no slack): (wall time,
    success, iterations, the solution for the next call or None, the first input)."""
    guess = previous
    if guess is None:
        guess = (
            np.tile(x[:, None], (1, N + 1)),
            np.tile(s.u_ref[:, None], (1, N)),
            np.zeros((s.nx, N + 1)),
        )
    t0 = time.perf_counter()
    try:
        out = fn(x, *guess)
        raised = False
    except RuntimeError:
        raised = True
    dt = time.perf_counter() - t0
    stats = fn.stats()
    ok = not raised and bool(stats.get("success", False))
    solution = tuple(np.asarray(o) for o in out) if ok else None
    u0 = solution[1][:, 0].copy() if ok else None
    return dt, ok, int(stats.get("iter_count", 0)), solution, u0


class FatropBaseline:
    """The same MPC as an expert's fatrop NMPC: ``casadi.Opti`` with the variables declared stage
    by stage (``x_i``, then ``u_i`` and the slacks ``eta_i``) and each stage's model equation
    ``x_{i+1} == F(x_i, u_i)`` before its path constraints, so that CasADi's structure detection
    (``structure_detection="auto"``) hands fatrop its stage-wise form; the NLP functions expanded
    to SX and compiled (``jit``, generated C, ``-O2``, built once per run); fatrop with the
    tolerance of our MPC; warm start: the previous step's primal solution (fatrop takes no dual
    warm start). Called through ``Opti.to_function``; the solve call alone is timed.
    """

    def __init__(self, s, model: str = "imperfect") -> None:
        spec = s.mpc_spec
        N, gamma, nx, nu = spec.horizon, spec.gamma, s.nx, s.nu
        Gamma = np.full(nx, 1e5) if spec.Gamma is None else np.asarray(spec.Gamma)
        Gamma_f = Gamma if spec.Gamma_f is None else np.asarray(spec.Gamma_f)
        pm = ca.DM(s.model_params(model))
        th, b = s.parameterization.theta0, s.parameterization.blocks
        Tw, G, Qw, Rw = th[b["T"]], th[b["G"]], th[b["Q"]], th[b["R"]]
        opti = ca.Opti()
        x0 = opti.parameter(nx)
        X, U, E = [], [], []
        for i in range(N + 1):  # stage-wise declaration: x_i, u_i, eta_i
            X.append(opti.variable(nx))
            if i < N:
                U.append(opti.variable(nu))
            E.append(opti.variable(nx))
        xr, ur = ca.DM(s.x_ref), ca.DM(s.u_ref)
        cost = th[b["theta_c"]][0]
        for i in range(N + 1):
            dx = X[i] - xr
            if i < N:  # the gap-closing constraint first
                opti.subject_to(X[i + 1] == rk4_step(s.dynamics, X[i], U[i], pm, s.dt, s.substeps))
            if i == 0:
                opti.subject_to(X[0] == x0)
            opti.subject_to(E[i] >= 0)
            opti.subject_to(X[i] >= ca.DM(s.x_lb) - E[i])
            opti.subject_to(X[i] <= ca.DM(s.x_ub) + E[i])
            if i < N:
                du = U[i] - ur
                opti.subject_to(opti.bounded(ca.DM(s.u_lb), U[i], ca.DM(s.u_ub)))
                cost += gamma**i * (
                    ca.dot(dx, Qw * dx) + ca.dot(du, Rw * du) + ca.dot(ca.DM(Gamma), E[i])
                )
                cost += ca.dot(ca.DM(G), ca.vertcat(dx, du))
            else:
                cost += ca.dot(ca.DM(G[:nx]), dx)
                cost += gamma**N * (ca.dot(dx, Tw * dx) + ca.dot(ca.DM(Gamma_f), E[i]))
        opti.minimize(cost)
        opti.solver(
            "fatrop",
            {
                "expand": True,
                "structure_detection": "auto",
                "print_time": False,
                "show_eval_warnings": False,
                "jit": True,
                "compiler": "shell",
                "jit_options": {"flags": ["-O2"], "verbose": False},
                "fatrop": {"print_level": 0, "tol": TOL},
            },
        )
        Xs, Us, Es = ca.horzcat(*X), ca.horzcat(*U), ca.horzcat(*E)
        self._fn = opti.to_function("fatrop_baseline", [x0, Xs, Us, Es], [Xs, Us, Es])
        self.N, self.s, self._prev = N, s, None

    def reset(self) -> None:
        self._prev = None

    def solve(self, x):
        """Returns (wall time of the solve call, success, iterations, first input)."""
        dt, ok, iters, self._prev, u0 = solve_warm(self._fn, x, self._prev, self.s, self.N)
        return dt, ok, iters, u0


class MpcrlPeer:
    """The same MPC in ``mpcrl`` 1.4.1 (``csnlp.wrappers.Mpc``), driven by an ``LstdDpgAgent``.

    Physical units as the baseline; the cost weights (theta_c, T, G, Q, R at theta0) are the
    agent's learnable parameters; IPOPT expanded to SX with our tolerances, the agent's own warm
    start ("last-successful"). One step = ``agent.state_value(x, deterministic=True)`` (the solve)
    plus the agent's dpi/dtheta for that solution (its ``_sensitivity`` function, which the agent
    evaluates once per rollout: timed per episode and spread evenly over its steps). No dV/dtheta
    (the agent does not compute it).
    """

    def __init__(self, s, model: str = "imperfect") -> None:
        from csnlp import Nlp
        from csnlp.wrappers import Mpc
        from mpcrl import LearnableParameter, LearnableParametersDict, LstdDpgAgent
        from mpcrl import exploration as E
        from mpcrl.optim import GradientDescent

        spec = s.mpc_spec
        N, gamma, nx, nu = spec.horizon, spec.gamma, s.nx, s.nu
        Gamma = np.full(nx, 1e5) if spec.Gamma is None else np.asarray(spec.Gamma)
        Gamma_f = Gamma if spec.Gamma_f is None else np.asarray(spec.Gamma_f)
        pm = ca.DM(s.model_params(model))
        th0 = s.parameterization.theta0
        blocks = s.parameterization.blocks
        mpc = Mpc(Nlp(sym_type="SX"), N)
        par = {
            n: mpc.parameter(n, (len(th0[blocks[n]]), 1)) for n in ("theta_c", "T", "G", "Q", "R")
        }
        x, _ = mpc.state("x", nx)
        u, _ = mpc.action("u", nu, lb=s.u_lb.reshape(-1, 1), ub=s.u_ub.reshape(-1, 1))
        eta, _, _ = mpc.variable("eta", (nx, N + 1), lb=0)
        xs, us = ca.SX.sym("x", nx), ca.SX.sym("u", nu)
        mpc.set_nonlinear_dynamics(ca.Function("F", [xs, us], [s.discrete_step(xs, us, pm)]))
        mpc.constraint("x_lb", ca.DM(s.x_lb) - eta, "<=", x)
        mpc.constraint("x_ub", x, "<=", ca.DM(s.x_ub) + eta)
        xr, ur = ca.DM(s.x_ref), ca.DM(s.u_ref)
        cost = par["theta_c"]
        for i in range(N + 1):
            dx = x[:, i] - xr
            if i < N:
                du = u[:, i] - ur
                cost += gamma**i * (
                    ca.dot(dx, par["Q"] * dx)
                    + ca.dot(du, par["R"] * du)
                    + ca.dot(ca.DM(Gamma), eta[:, i])
                )
                cost += ca.dot(par["G"], ca.vertcat(dx, du))
            else:
                cost += ca.dot(par["G"][:nx], dx)
                cost += gamma**N * (ca.dot(dx, par["T"] * dx) + ca.dot(ca.DM(Gamma_f), eta[:, i]))
        mpc.minimize(cost)
        mpc.init_solver(
            {
                "expand": True,
                "print_time": False,
                "show_eval_warnings": False,
                "calc_lam_p": False,
                "ipopt": {
                    "print_level": 0,
                    "sb": "yes",
                    "tol": TOL,
                    "acceptable_tol": ACCEPTABLE_TOL,
                },
            },
            solver="ipopt",
        )
        learnable = LearnableParametersDict(
            LearnableParameter(n, (len(th0[blocks[n]]), 1), th0[blocks[n]].reshape(-1, 1))
            for n in par
        )
        self.agent = LstdDpgAgent(
            mpc=mpc,
            update_strategy=10**9,
            discount_factor=gamma,
            optimizer=GradientDescent(learning_rate=0.0),
            learnable_parameters=learnable,
            exploration=E.OrnsteinUhlenbeckExploration(0.0, 0.0, mode="additive"),
        )
        self._vals: list = []
        self._s, self._N = s, N
        self._first = True

    def reset(self) -> None:
        self.agent.reset()
        self._vals = []
        self._first = True

    def solve(self, x):
        """Returns (wall time of the solve, success, iterations, first input)."""
        vals0 = None
        if self._first:  # the baseline's cold guess; later the agent warm-starts by itself
            N, s = self._N, self._s
            vals0 = {
                "x": np.tile(x[:, None], (1, N + 1)),
                "u": np.tile(s.u_ref[:, None], (1, N)),
                "eta": np.zeros((s.nx, N + 1)),
            }
        t0 = time.perf_counter()
        action, sol = self.agent.state_value(x, deterministic=True, vals0=vals0)
        dt = time.perf_counter() - t0
        self._first = self._first and not sol.success
        if sol.success:
            self._vals.append(np.asarray(sol.x_and_lam_and_p.elements()))
        it = int(sol.stats.get("iter_count", 0))
        return dt, bool(sol.success), it, np.asarray(action).reshape(-1)

    def episode_sensitivity_time(self) -> float:
        """Wall time of the agent's dpi/dtheta for the episode's successful solves, per solve."""
        if not self._vals:
            return 0.0
        vals = ca.DM(np.stack(self._vals))
        t0 = time.perf_counter()
        self.agent._sensitivity(vals, len(self._vals))
        return (time.perf_counter() - t0) / len(self._vals)


# name -> ParametricMPC options; the first one drives the closed loop.
VARIANTS: dict[str, dict] = {
    # up to 6 Newton steps on the barrier KKT system from the shifted previous solution, IPOPT
    # (shifted primal-dual warm start, no lam_p) when they do not converge; adjoint
    # sensitivities (sparse QR)
    "default": {},
    "ipopt": {"newton_steps": 0},  # IPOPT only
    # IPOPT only, with lam_p (the multipliers of the parameters: one more gradient evaluation
    # per solve, unused by the sensitivities)
    "ipopt_lam_p": {"newton_steps": 0, "solver_options": {"calc_lam_p": True}},
    "cold": {"warm_start": False},  # no warm start (so no Newton steps either)
    "warm_mu_init_1e-5": {"newton_steps": 0, "warm_options": {"mu_init": 1e-5}},
    "warm_mu_adaptive": {"newton_steps": 0, "warm_options": {"mu_strategy": "adaptive"}},
    "hess_lbfgs": {
        "newton_steps": 0,
        "solver_options": {"hessian_approximation": "limited-memory"},
    },
    # generated C, compiled once per machine and problem, cached on disk
    "codegen_ipopt": {"codegen": True, "newton_steps": 0},
    # generated C, the Newton steps, the continuation, then IPOPT (the default paths)
    "codegen": {"codegen": True},
    # without the continuation: IPOPT where the Newton steps do not get there
    "codegen_no_continuation": {"codegen": True, "continuation_steps": 0},
    "no_continuation": {"continuation_steps": 0},
}
DEFAULT_VARIANTS = list(VARIANTS)


# name -> OptiBaseline options; "baseline" is the reference of every ratio.
BASELINES: dict[str, dict] = {
    "baseline": {"expand": True},  # SX, Opti.to_function, warm: the expert's formulation
    "baseline_mx": {"expand": False},  # MX, opti.solve(), warm: an extra row
}
# the expert fatrop NMPC (FatropBaseline): a second reference, ratio_fatrop
_BASELINE_LABELS = {
    "baseline": "Opti, expand=True (SX), Opti.to_function, our tolerances",
    "baseline_mx": "Opti, MX, opti.solve(), our tolerances",
    "fatrop": "Opti, stage-wise, structure detection, fatrop, jit -O2, our tolerance",
    "mpcrl": "mpcrl 1.4.1 LstdDpgAgent: state_value + its dpi/dtheta per step",
}


class _Components:
    """Wall time of an MPC's solver calls (IPOPT and Newton steps), of its sensitivities and of
    IPOPT's function evaluations (its own statistics) during one ``solve``."""

    def __init__(self, mpc: ParametricMPC) -> None:
        self.solver = self.sens = self.fun = 0.0
        solver = mpc.solver
        run_solver, sensitivities = solver.ipopt, solver.sensitivities
        newton, interior_point = solver.newton, solver.interior_point

        def timed_run(x, p, warm):
            t0 = time.perf_counter()
            out = run_solver(x, p, warm)
            self.solver += time.perf_counter() - t0
            st = (solver.warm if warm else solver.cold).stats()
            self.fun += sum(v for k, v in st.items() if k.startswith("t_wall_nlp"))
            return out

        def timed_sens(*args):
            t0 = time.perf_counter()
            try:
                return sensitivities(*args)
            finally:
                self.sens += time.perf_counter() - t0

        def timed(fn):
            def run(*args):
                t0 = time.perf_counter()
                try:
                    return fn(*args)
                finally:
                    self.solver += time.perf_counter() - t0

            return run

        # the solver's path methods, replaced on this instance by timed wrappers
        solver.ipopt, solver.sensitivities = timed_run, timed_sens
        solver.newton, solver.interior_point = timed(newton), timed(interior_point)

    def take(self) -> tuple[float, float, float]:
        out = (self.solver, self.sens, self.fun)
        self.solver = self.sens = self.fun = 0.0
        return out


def run(
    episodes: int, steps: int, variants: dict[str, dict], seed: int = 0, peers: bool = True
) -> dict:
    s = get_system("cstr")
    build = {}
    mpcs = {}
    for name, opts in variants.items():
        t0 = time.perf_counter()
        mpcs[name] = ParametricMPC(s, "imperfect", **opts)
        build[name] = time.perf_counter() - t0
    comps = {n: _Components(m) for n, m in mpcs.items()}
    bases = {name: OptiBaseline(s, **opts) for name, opts in BASELINES.items()}
    bases["fatrop"] = FatropBaseline(s)
    if peers and _has_mpcrl():
        bases["mpcrl"] = MpcrlPeer(s)
    names = [*mpcs, *bases]
    times = {n: [] for n in names}
    parts = {n: [] for n in mpcs}  # (solver, sensitivities, function evaluations) per step
    iters = {n: [] for n in names}
    fails = {n: 0 for n in names}
    du = {n: [] for n in mpcs}  # |action - baseline action|, a sanity check of "same problem"
    du_first = {n: [] for n in names}  # |action - first variant's action|: "same policy"
    du_ipopt: dict[str, list] = {n: [] for n in mpcs}  # |action - the "ipopt" variant's action|
    path_names = {
        "Newton_Succeeded": "newton",
        "Continuation_Succeeded": "continuation",
        "Restart_Continuation_Succeeded": "restart",
        "Cold_Continuation_Succeeded": "cold",
    }
    # which path solved
    paths = {n: {k: 0 for k in [*path_names.values(), "ipopt"]} for n in mpcs}
    path_times = {n: {k: [] for k in paths[n]} for n in mpcs}  # step times by path
    rng = np.random.default_rng(seed)
    x0s = [s.sample_initial_state(rng) for _ in range(episodes)]
    order_rng = np.random.default_rng(seed + 1)
    theta0 = next(iter(mpcs.values())).theta0
    first = names[0]
    # one untimed solve per variant and baseline (first-call allocations)
    for m in mpcs.values():
        m.solve(x0s[0], theta0, sensitivities=True)
        m.reset()
    for c in comps.values():
        c.take()
    for b in bases.values():
        b.solve(x0s[0])
        b.reset()
    for x0 in x0s:
        for m in mpcs.values():
            m.reset()
        for b in bases.values():
            b.reset()
        x = x0.copy()
        episode_steps = {n: [] for n in bases}
        for _ in range(steps):
            # a new random order every step (seeded): with a rotation the variants kept their
            # neighbours, and one that ran after another calling the same compiled library
            # found its code in warm caches (docs/benchmarks.md, step time)
            order = [names[i] for i in order_rng.permutation(len(names))]
            actions = {}
            for n in order:
                if n in bases:
                    dt, ok, it, u0 = bases[n].solve(x)
                    actions[n] = u0
                    episode_steps[n].append(len(times[n]))
                else:
                    t0 = time.perf_counter()
                    sol = mpcs[n].solve(x, theta0, sensitivities=True)
                    dt = time.perf_counter() - t0
                    parts[n].append(comps[n].take())
                    ok, it = sol.success, sol.iterations
                    path = path_names.get(sol.status, "ipopt")
                    paths[n][path] += 1
                    path_times[n][path].append(dt)
                    actions[n] = sol.action
                    ok = ok and bool(np.all(np.isfinite(sol.dpi_dtheta)))
                times[n].append(dt)
                iters[n].append(it)
                fails[n] += not ok
            if actions["baseline"] is not None:
                for n in mpcs:
                    du[n].append(float(np.max(np.abs(actions[n] - actions["baseline"]))))
            if "ipopt" in mpcs:
                for n in mpcs:
                    du_ipopt[n].append(float(np.max(np.abs(actions[n] - actions["ipopt"]))))
            for n in names:
                if actions[n] is not None and actions[first] is not None:
                    du_first[n].append(float(np.max(np.abs(actions[n] - actions[first]))))
            x = s.plant_step(x, actions[first])
        if "mpcrl" in bases:  # its sensitivities, evaluated once per episode, spread evenly
            per_step = bases["mpcrl"].episode_sensitivity_time()
            for i in episode_steps["mpcrl"]:
                times["mpcrl"][i] += per_step
    med = {n: float(np.median(times[n])) for n in names}
    res = {}
    for n in names:
        t = np.array(times[n]) * 1e3
        if n in bases:  # this baseline's solve / our first variant's step
            ratio = {"ratio": med[n] / med[first]}
        else:  # a baseline's solve / this variant's step
            ratio = {
                "ratio": med["baseline"] / med[n],
                "ratio_mx": med["baseline_mx"] / med[n],
                "ratio_fatrop": med["fatrop"] / med[n],
            }
        res[n] = {
            "median_ms": float(np.median(t)),
            "p95_ms": float(np.percentile(t, 95)),
            "mean_ms": float(np.mean(t)),
            "mean_iters": float(np.mean(iters[n])),
            "failures": int(fails[n]),
            **ratio,
            "max_du_vs_baseline": float(np.max(du[n])) if n in du and du[n] else None,
            # against our IPOPT-only variant (the same barrier problem), when it runs: the
            # largest difference and the steps where the actions differ by more than 1e-7, 1e-4
            "max_du_vs_ipopt": float(np.max(du_ipopt[n])) if du_ipopt.get(n) else None,
            "n_du_vs_ipopt_gt_1e-7": int(np.sum(np.array(du_ipopt.get(n, [])) > 1e-7)),
            "n_du_vs_ipopt_gt_1e-4": int(np.sum(np.array(du_ipopt.get(n, [])) > 1e-4)),
            "max_du_vs_first": float(np.max(du_first[n])) if du_first[n] else None,
            # steps where the action differs from the first variant's by more than 1e-4
            "n_du_vs_first_gt_1e-4": int(np.sum(np.array(du_first[n]) > 1e-4)),
            "variant": variants.get(n, _BASELINE_LABELS.get(n)),
        }
        if n in mpcs:
            a = np.array(parts[n]) * 1e3
            res[n].update(
                build_s=build[n],
                median_solver_ms=float(np.median(a[:, 0])),
                median_sens_ms=float(np.median(a[:, 1])),
                median_fun_ms=float(np.median(a[:, 2])),
                median_other_ms=float(np.median(t - a[:, 0] - a[:, 1])),
                paths=paths[n],
                # median step time [ms] of the steps each path solved (None: no such step)
                median_ms_by_path={
                    k: float(np.median(v) * 1e3) if v else None for k, v in path_times[n].items()
                },
            )
    return res


def _has_mpcrl() -> bool:
    try:
        import mpcrl  # noqa: F401
    except ImportError:
        return False
    return True


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="1 episode of 20 steps")
    ap.add_argument("--episodes", type=int, default=4)
    ap.add_argument("--steps", type=int, default=60)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument(
        "--variants",
        nargs="*",
        default=None,
        help=f"subset of {list(VARIANTS)} (default: all)",
    )
    ap.add_argument("--json", default=None, help="write the results to this file")
    ap.add_argument("--no-peers", action="store_true", help="without the mpcrl row")
    args = ap.parse_args(argv)
    episodes, steps = (1, 20) if args.quick else (args.episodes, args.steps)
    names = args.variants or DEFAULT_VARIANTS
    unknown = [v for v in names if v not in VARIANTS]
    if unknown:
        ap.error(f"unknown variant(s) {unknown}; choose from {list(VARIANTS)}")
    variants = {k: VARIANTS[k] for k in names}
    res = run(episodes, steps, variants, args.seed, peers=not args.no_peers)
    print(
        f"CSTR, {episodes} episode(s) x {steps} steps, casadi {ca.__version__}, "
        f"{platform.machine()}, python {platform.python_version()}"
    )
    first = next(iter(variants))
    print(
        f"ratio: baseline median / variant median (on a baseline row: that baseline's median / "
        f"{first!r} median); ratio_fat: the same against the expert fatrop NMPC"
    )
    print(
        "du_ipopt: largest |action - the 'ipopt' variant's action| (the same barrier problem, "
        "IPOPT only); >1e-7, >1e-4: steps beyond. components "
        "(medians, ms): solver = Newton steps, continuation and IPOPT calls, sens = both "
        "sensitivities, other = the rest of the step (Python). paths: steps solved by "
        "Newton / continuation / restarted continuation / cold continuation / IPOPT"
    )
    hdr = (
        f"{'variant':<24} {'median':>7} {'mean':>7} {'p95':>7} {'iters':>6} {'fail':>4} "
        f"{'ratio':>6} {'ratio_fat':>9} {'du_ipopt':>8} {'>1e-7':>5} {'>1e-4':>5} "
        f"{'solver':>6} {'sens':>6} {'other':>6} {'build s':>7} {'paths':>14}"
    )
    print(hdr)
    for n, r in res.items():
        rf = f"{r['ratio_fatrop']:>9.2f}" if "ratio_fatrop" in r else f"{'':>9}"
        dub = r.get("max_du_vs_ipopt")
        dub_s = (
            f"{dub:>8.1e} {r['n_du_vs_ipopt_gt_1e-7']:>5d} {r['n_du_vs_ipopt_gt_1e-4']:>5d}"
            if dub is not None
            else " " * 20
        )
        comp = (
            f"{r['median_solver_ms']:>6.2f} {r['median_sens_ms']:>6.2f} "
            f"{r['median_other_ms']:>6.2f} {r['build_s']:>7.2f} "
            f"{'/'.join(str(v) for v in r['paths'].values()):>14}"
            if "build_s" in r
            else ""
        )
        print(
            f"{n:<24} {r['median_ms']:>7.2f} {r['mean_ms']:>7.2f} {r['p95_ms']:>7.2f} "
            f"{r['mean_iters']:>6.1f} {r['failures']:>4d} {r['ratio']:>6.2f} {rf} "
            f"{dub_s} {comp}"
        )
    print(
        "median step [ms] by the path that solved it (Newton / continuation / restart / cold / IPOPT):"
    )
    for n, r in res.items():
        if "median_ms_by_path" in r:
            by = r["median_ms_by_path"].values()
            print(f"  {n:<24} " + " / ".join("-" if v is None else f"{v:.2f}" for v in by))
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=2, default=str)


if __name__ == "__main__":
    main()
