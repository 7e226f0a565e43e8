"""The tuned MPC as a self-contained embedded controller: C that needs only libc and libm.

:func:`export_embedded` writes into a directory

- ``mpc_functions.c`` / ``.h``: CasADi-generated code of the MPC's Newton step on the barrier KKT
  system at ``tau`` (``mpcmobo_newton``) and at a barrier parameter ``m``
  (``mpcmobo_newton_mu``), the rows ``H(w, p)`` (``mpcmobo_rows``), the reduced Hessian whose
  Cholesky factorisation tells a minimum from a saddle point (``mpcmobo_reduced_hessian``,
  :meth:`~mpcmobo.mpc.kkt.KKTSystem.is_minimum`) and the one-stage shift of a root into the
  next warm start with its multipliers (``mpcmobo_warm_start``); the linear solves are
  CasADi's sparse QR, generated as plain C; every name it exports begins with ``mpcmobo_``
  or ``mpc_functions_``;
- ``controller.c`` / ``.h``: the solve, the paths of :mod:`mpcmobo.mpc.solve` without IPOPT:
  with a warm start, at most ``newton_steps`` Newton steps, then the interior-point
  continuation of :mod:`mpcmobo.mpc.interior` from the re-centred shifted plan, then the same
  restarted from the shifted plan on the central path; without one (the first call, or after
  a failure), and where those do not get there, the continuation from the cold guess of
  :meth:`~mpcmobo.mpc.transcription.Transcription.cold_guess`, re-centred, on the central path
  at ``m`` = 1, then 0.1; a continuation's root is taken only at a minimum, as the MPC takes
  it; where no path gets there, the fallback input: the previous plan's next input, else
  ``u_r`` (return value 1). theta is fixed; every array is static (no ``malloc``), every loop
  bounded;
- ``main.c``: reads one state per line from the standard input, prints the input and the
  step's wall time in microseconds (``clock_gettime``).

Build it with :func:`embedded_compile_command` (``cc -O2 ... -lm``), for another target with
its cross compiler (``docs/real-plant.md``).
"""

from __future__ import annotations

import os
from pathlib import Path

import casadi as ca
import numpy as np

from mpcmobo.mpc.codegen import compiler_command
from mpcmobo.mpc.embedded_source import CONTROLLER_C, CONTROLLER_H, MAIN_C
from mpcmobo.mpc.export import check_generated, quiet_unused
from mpcmobo.mpc.interior import RESTART_BARRIER
from mpcmobo.mpc.parametric import ParametricMPC

__all__ = ["embedded_compile_command", "export_embedded", "warm_start_function"]


def warm_start_function(mpc: ParametricMPC) -> ca.Function:
    """``warm_start(y) -> y0``: a root ``y = (w, lambda, mu)`` of the KKT residual shifted by one
    stage, with the multipliers the solver recovers from it (``Transcription.shifted`` of
    ``KKTSystem.solver_outputs``, then ``KKTSystem.multipliers``), as one SX function."""
    pr, kkt = mpc.problem, mpc.kkt
    nw, neq, nin, n_lb = pr.nw, pr.neq, pr.nin, len(kkt.lb_idx)
    y = ca.SX.sym("y", kkt.ny)
    w, lam, mu = y[:nw], y[nw : nw + neq], y[nw + neq :]
    lam_g = ca.vertcat(lam, mu[:nin])
    lam_x = ca.SX.zeros(nw)
    for j, i in enumerate(kkt.ub_idx.tolist()):
        lam_x[i] += mu[nin + n_lb + j]
    for j, i in enumerate(kkt.lb_idx.tolist()):
        lam_x[i] -= mu[nin + j]
    w_s, lg, lx = w[pr.wshift.tolist()], lam_g[pr.gshift.tolist()], lam_x[pr.wshift.tolist()]
    tiny, tau = 1e-300, kkt.tau
    zL, zU = [], []
    for i in range(nw):
        lo, hi = float(pr.lbw[i]), float(pr.ubw[i])
        zl, zu = ca.fmax(-lx[i], 0.0), ca.fmax(lx[i], 0.0)
        if np.isfinite(lo) and np.isfinite(hi):  # the far bound's multiplier from tau
            gap_l, gap_u = w_s[i] - lo, hi - w_s[i]
            near_l = gap_l <= gap_u
            zu_l = tau / ca.fmax(gap_u, tiny)
            zl_u = tau / ca.fmax(gap_l, tiny)
            zl, zu = ca.if_else(near_l, zu_l - lx[i], zl_u), ca.if_else(near_l, zu_l, lx[i] + zl_u)
        zL.append(zl)
        zU.append(zu)
    mu0 = ca.vertcat(
        ca.fmax(lg[neq:], tiny),
        *[ca.fmax(zL[i], tiny) for i in kkt.lb_idx.tolist()],
        *[ca.fmax(zU[i], tiny) for i in kkt.ub_idx.tolist()],
    )
    return ca.Function("warm_start", [y], [ca.vertcat(w_s, lg[:neq], mu0)])


def _c_array(ctype: str, name: str, values: np.ndarray) -> str:
    vals = np.asarray(values).reshape(-1)
    if ctype == "double":
        body = ", ".join(repr(float(v)) for v in vals) if len(vals) else "0"
    else:
        body = ", ".join(str(int(v)) for v in vals) if len(vals) else "0"
    return f"static const {ctype} {name}[{max(len(vals), 1)}] = {{{body}}};\n"


def _constants(mpc: ParametricMPC, theta: np.ndarray, functions: list[ca.Function]) -> str:
    """The C definitions of the sizes, theta, the layout and the settings."""
    pr, kkt, sysm, solver = mpc.problem, mpc.kkt, mpc.system, mpc.solver
    interior = solver.interior
    slack = kkt.slack_of_row
    groups = [np.flatnonzero(slack == k) for k in np.unique(slack[slack >= 0])]
    ptr = np.cumsum([0] + [len(g) for g in groups])
    sz = [f.sz_w() for f in functions]
    out = [
        f"#define NX {pr.nx}\n#define NU {pr.nu}\n#define NW {pr.nw}\n#define NEQ {pr.neq}\n",
        f"#define NH {kkt.nH}\n#define NY {kkt.ny}\n#define NP {pr.nx + pr.n_theta}\n",
        f"#define NSLACK {len(groups)}\n#define NSTAGE {pr.N}\n",
        f"#define NRED {pr.nw - pr.neq}\n",
        f"#define SZ_ARG {max(f.sz_arg() for f in functions)}\n",
        f"#define SZ_RES {max(f.sz_res() for f in functions)}\n",
        f"#define SZ_IW {max(f.sz_iw() for f in functions)}\n#define SZ_W {max(sz)}\n",
        f"#define TAU {kkt.tau!r}\n#define TOL {solver.tol!r}\n",
        f"#define NEWTON_STEPS {solver.newton_steps}\n",
        f"#define MAX_STEPS {interior.max_steps if interior else 30}\n",
        f"#define GAP {(interior.gap if interior else 1e-3)!r}\n",
        f"#define DELTA {(interior.delta if interior else 1e-2)!r}\n",
        f"#define M0 {(interior.m0 if interior else 1e-3)!r}\n",
        f"#define RESTART_M0 {RESTART_BARRIER!r}\n",
        f"#define KAPPA {(interior.kappa if interior else 10.0)!r}\n",
        _c_array("double", "THETA", theta),
        _c_array("int", "SLACK_VAR", np.unique(slack[slack >= 0])),
        _c_array("int", "SLACK_PTR", ptr),
        _c_array("int", "SLACK_ROWS", np.concatenate(groups) if groups else np.zeros(0)),
        _c_array("int", "ROW_SLACK", slack),
        _c_array("int", "IU", np.asarray(pr.iu_flat)),
        _c_array("int", "IX", np.asarray(pr.ix_flat)),
        _c_array("double", "X_REF", sysm.x_ref),
        _c_array("double", "SX_", pr.Sx),
        _c_array("double", "U_REF", sysm.u_ref),
        _c_array("double", "SU", pr.Su),
        _c_array("double", "U_LB", sysm.u_lb),
        _c_array("double", "U_UB", sysm.u_ub),
    ]
    return "".join(out)


#: what the names the generated C exports begin with (``mpcmobo_newton``, ``mpcmobo_rows``,
#: ...): a control task's own ``newton`` or ``rows`` links beside them
PREFIX = "mpcmobo_"


def _prefixed(f: ca.Function) -> ca.Function:
    """``f`` under the name ``PREFIX + f.name()``: an SX function's expressions again, an MX
    function called by a wrapper (CasADi's generated code keeps a called function static)."""
    name = PREFIX + f.name()
    if f.is_a("SXFunction"):
        sx = f.sx_in()
        return ca.Function(name, sx, f.call(sx), f.name_in(), f.name_out())
    mx = f.mx_in()
    return ca.Function(name, mx, f.call(mx), f.name_in(), f.name_out())


def export_embedded(
    mpc: ParametricMPC, theta: np.ndarray | None, directory: str | os.PathLike
) -> Path:
    """Write the embedded controller of ``mpc`` with ``theta`` (default theta0) into
    ``directory`` (made if missing; module docstring); returns the directory."""
    theta = mpc.check_theta(theta)
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    kkt = mpc.kkt
    functions = [
        kkt.newton,
        kkt.newton_mu,
        kkt.rows,
        kkt.reduced_hessian,
        warm_start_function(mpc),
    ]
    if not all(isinstance(f, ca.Function) and not f.is_a("external") for f in functions):
        raise ValueError("export_embedded needs the MPC's own functions (build it without codegen)")
    functions = [_prefixed(f) for f in functions]
    gen = ca.CodeGenerator("mpc_functions.c", {"with_header": True})
    for f in functions:
        gen.add(f)
    gen.generate(str(directory) + os.sep)
    generated = [directory / "mpc_functions.c", directory / "mpc_functions.h"]
    check_generated(generated[0], generated)
    quiet_unused(generated[0])
    constants = _constants(mpc, theta, functions)
    (directory / "controller.h").write_text(CONTROLLER_H)
    (directory / "controller.c").write_text(CONTROLLER_C.replace("/* CONSTANTS */\n", constants))
    (directory / "main.c").write_text(MAIN_C)
    return directory


def embedded_compile_command(
    directory: str | os.PathLike, output: str = "controller", optimize: str = "-O2"
) -> list[str]:
    """The command that builds the embedded controller of ``directory`` with its ``main.c``
    into the program ``output`` (``$CC`` or ``cc``, ``optimize``, libm)."""
    d = Path(directory)
    sources = [str(d / n) for n in ("controller.c", "mpc_functions.c", "main.c")]
    return [*compiler_command(), optimize, *sources, "-lm", "-o", str(d / output)]
