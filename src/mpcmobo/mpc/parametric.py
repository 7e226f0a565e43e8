"""The parametric NMPC of eq. (V0): policy (eq. Policy), value and their KKT sensitivities.

The optimal control problem, with the cost of section 5 of the paper::

    V_theta(x) = min  theta_c + sum_{i<N} gamma^i [ |x_i - x_r|^2_Q + |u_i - u_r|^2_R + Gamma^T eta_i ]
                      + sum_{i<N} G^T [x_i - x_r; u_i - u_r] + G_x^T (x_N - x_r)
                      + gamma^N [ |x_N - x_r|^2_T + Gamma_f^T eta_N ]                  (eq. cost_mpc)
         s.t.  x_{i+1} = f_hat_theta(x_i, u_i)                                        (eq. mpc_model)
               x_0 = x                                                                (eq. v2)
               u_lb <= u_i <= u_ub                                 (pure input bounds g(u) <= 0)
               x_lb + b_lb - eta_i <= x_i <= x_ub - b_ub + eta_i, i = 0..N           (eq. violation)
               eta_i >= 0                                                             (eq. slack)
               h(x_i, u_i) <= eta^h_i, eta^h_i >= 0, i = 0..N (u_N := u_{N-1})   (path constraints)

A system's general path constraints ``h(x, u) <= 0`` are relaxed like the state bounds, with
slacks ``eta^h`` penalised by ``Gamma_h`` (l1) in the stage and terminal costs. With
``MPCSpec.full_weights`` the weights ``T``, ``Q``, ``R`` are full matrices ``L L^T`` from the
Cholesky entries in theta; otherwise diagonal as written above.

The linear term ``G`` acts on deviations from the reference (the paper writes it on ``[x, u]``;
the two differ by a constant, so the policy is the same and the value is better scaled).

Decision variables are scaled, ``x = x_r + S_x z_x``, ``u = u_r + S_u z_u``, ``eta = S_x z_eta``,
and the cost is divided by ``cost_scale``; values and sensitivities are returned in physical units.

Sensitivities (eq. nabla_pi). IPOPT is run to the barrier parameter ``tau`` (option ``mu_target``),
so its solution is exactly the root of the barrier-relaxed primal-dual KKT residual::

    R(y, p) = [ grad_zeta Lagr ;  G ;  diag(mu) H + tau ],   y = (zeta, lambda, mu),

with ``Lagr = Phi + lambda^T G + mu^T H`` and ``H <= 0`` collecting every inequality (general and
simple bounds). ``R`` is smooth across active-set changes and ``dR/dy`` stays invertible, so

    d pi / d theta = - (dR/dtheta)^T (dR/dy)^{-T} e_{u_0}                             (eq. nabla_pi)
    d V  / d theta = d Lagr / d theta at the solution                                  (grad V)

and the finite differences of the solver's own outputs agree with them.

The same residual gives a fast path for warm solves (``newton_steps``): from the shifted
previous solution, Newton steps ``dR/dy dy = -R`` with a fraction-to-boundary rule reach the
root of ``R`` in 3-4 steps when the active set does not change; accepted at ``|R| <= tol`` at a
strictly interior point, it is the point IPOPT stops at. IPOPT solves when they do not converge.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, NamedTuple

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from mpcmobo.mpc.codegen import compiled_library
from mpcmobo.systems.base import System
from mpcmobo.systems.parameterization import Parameterization, weight_matrix

_SUCCESS = frozenset({"Solve_Succeeded", "Solved_To_Acceptable_Level"})
# options of CasADi's nlpsol itself (not IPOPT's): passed without the "ipopt." prefix
_CASADI_NLPSOL_KEYS = (
    "print_time",
    "show_eval_warnings",
    "calc_lam_p",
    "calc_lam_x",
    "calc_f",
    "calc_g",
    "bound_consistency",
    "record_time",
)


@dataclass
class MPCSolution:
    """Result of one MPC solve at state ``x`` with parameters ``theta``."""

    action: np.ndarray  # (nu,) pi_theta(x), or the fallback input when the solve failed
    value: float  # V_theta(x) (NaN when failed)
    dpi_dtheta: np.ndarray | None  # (n_theta, nu)
    dV_dtheta: np.ndarray | None  # (n_theta,)
    success: bool
    status: str
    slack: float = 0.0  # sum of the slacks eta, physical units
    iterations: int = 0
    plan_u: np.ndarray | None = None  # (N, nu) predicted inputs
    plan_x: np.ndarray | None = None  # (N+1, nx) predicted states
    solve_time: float = 0.0  # seconds, solve + sensitivities
    fallback: bool = False
    info: dict = field(default_factory=dict)


def _fraction_to_boundary(mu: ca.MX, dmu: ca.MX, H: ca.MX, dH: ca.MX) -> ca.MX:
    """The step length ``a <= 1`` of a Newton step after which the multipliers ``mu + a dmu``
    and (to first order) the inequalities ``H + a dH`` keep 0.5 % of their distance to 0."""
    big = ca.DM(1e300)
    a_mu = ca.mmin(ca.if_else(dmu < 0, -mu / dmu, big))
    a_H = ca.mmin(ca.if_else(dH > 0, -H / dH, big))
    return ca.fmin(1.0, 0.995 * ca.fmin(a_mu, a_H))


class _NumpyCall:
    """A CasADi function evaluated into preallocated numpy arrays: ``f(*args)`` returns its
    outputs (2-d arrays in the function's shapes, floats for scalars), the numbers of ``fn(*args)``
    bit for bit, without converting every argument and result to a ``DM`` (that conversion was
    half the time of a compiled Newton step's call). The buffers are made at the first call, so
    a fresh MPC holds plain CasADi functions only. The returned arrays are copies."""

    def __init__(self, fn: ca.Function) -> None:
        self.fn = fn
        self._state: tuple | None = None

    def _setup(self) -> tuple:
        fn = self.fn
        buf, run = fn.buffer()
        args = []
        for i in range(fn.n_in()):
            if fn.nnz_in(i) != fn.numel_in(i):  # not expected: every input here is dense
                raise ValueError(f"{fn.name()}: input {i} is sparse")
            args.append(np.zeros(fn.nnz_in(i)))
            # CasADi's stubs ask for a size the Python binding takes from the buffer itself
            buf.set_arg(i, memoryview(args[-1]))  # type: ignore[call-arg, arg-type]
        res, shapes = [], []
        for i in range(fn.n_out()):
            sp = fn.sparsity_out(i)
            res.append(np.zeros(sp.nnz()))
            buf.set_res(i, memoryview(res[-1]))  # type: ignore[call-arg, arg-type]
            dense = sp.nnz() == sp.numel()
            shapes.append((sp.size1(), sp.size2(), None if dense else np.array(sp.find())))
        self._state = (buf, run, args, res, shapes)
        return self._state

    def __call__(self, *values: Any) -> tuple:
        _, run, args, res, shapes = self._state or self._setup()
        for a, v in zip(args, values):
            a[:] = v
        run()
        out: list = []
        for r, (n1, n2, nz) in zip(res, shapes):
            if nz is not None:  # structural zeros: scatter (column-major positions)
                d = np.zeros(n1 * n2)
                d[nz] = r
                r = d
            if n1 * n2 == 1:
                out.append(float(r[0]))
            else:
                out.append(r.reshape((n1, n2), order="F").copy())
        return tuple(out)


class ParametricMPC:
    """The MPC of eq. (V0) for a :class:`~mpcmobo.systems.System`, built once, solved many times.

    ``ParametricMPC(system, model="imperfect", **options)`` is the way to build the MPC of a
    system.

    Parameters
    ----------
    system:
        The system whose model, bounds, references and parameterization are used.
    model:
        ``"imperfect"``, ``"perfect"``, another name in ``system.models`` or a parameter vector.
    tau:
        Barrier parameter at which the problem is solved and differentiated (scaled units).
    tol:
        IPOPT tolerance on the barrier problem.
    warm_start:
        Initialise each solve from the shifted previous solution.
    solver_options:
        Extra IPOPT options (``{"max_iter": 200}``, ...), for the cold and the warm solver.
    warm_options:
        IPOPT options of the warm-started solver only (after the built-in warm-start settings).
    linsol:
        CasADi linear solver plugin of the sensitivity system (``"qr"``, the default and
        fastest measured, ``"csparse"``, ...), used in one adjoint solve inside a single CasADi
        function.
    codegen:
        Use generated C code for IPOPT's NLP functions, the sensitivity function and the Newton
        step, compiled once per machine and problem and cached on disk (``mpcmobo.mpc.codegen``):
        the first build compiles (tens of seconds), later builds of the same problem load the
        library. Same numbers as without it, faster steps (``docs/benchmarks.md``, step time).
        Needs a C compiler (``$CC`` or ``cc``).
    cache_dir:
        Directory of the compiled libraries (default: ``mpcmobo.mpc.codegen.cache_directory()``).
    newton_steps:
        With a warm start, first try at most this many Newton steps on the barrier KKT system
        ``R(y, p) = 0`` from the shifted previous solution (fraction-to-boundary steps that keep
        ``H < 0`` and ``mu > 0``). Accepted only when ``|R|_inf <= tol`` at a strictly interior
        point: then it is the barrier solution IPOPT stops at, to its tolerance; otherwise IPOPT
        solves as without it. 0: no Newton steps at the fixed tau.
    """

    def __init__(
        self,
        system: System,
        model: str | np.ndarray = "imperfect",
        *,
        horizon: int | None = None,
        gamma: float | None = None,
        tau: float = 1e-6,
        tol: float = 1e-8,
        max_iter: int = 150,
        warm_start: bool = True,
        solver_options: dict | None = None,
        cost_scale: float | None = None,
        warm_options: dict | None = None,
        linsol: str = "qr",
        codegen: bool = False,
        cache_dir: str | os.PathLike | None = None,
        newton_steps: int = 6,
    ) -> None:
        spec = system.mpc_spec
        self.system = system
        self.model = model if isinstance(model, str) else "custom"
        self.model_params = np.array(system.model_params(model), dtype=float)
        self.N = int(spec.horizon if horizon is None else horizon)
        self.gamma = float(spec.gamma if gamma is None else gamma)
        _check_options(self.N, self.gamma, tau, linsol)
        if int(newton_steps) != newton_steps or newton_steps < 0:
            raise ValueError(f"newton_steps must be an integer >= 0, got {newton_steps}")
        self._newton = int(newton_steps)
        self._tol = float(tol)
        self.tau = float(tau)
        self.warm_start = bool(warm_start)
        self.param: Parameterization = system.parameterization
        self.theta0 = self.param.theta0.copy()
        if "model" in self.param.blocks:  # learnable model parameters: this MPC's own model
            idx = list(self.param.model_param_index)
            self.theta0[self.param.blocks["model"]] = self.model_params[idx]
        self.theta_names = list(self.param.names)
        self.n_theta = self.param.n_theta
        self.nx, self.nu = system.nx, system.nu
        self.Sx, self.Su = np.asarray(system.x_scale, float), np.asarray(system.u_scale, float)
        self.Gamma = np.full(self.nx, 1e5) if spec.Gamma is None else np.asarray(spec.Gamma, float)
        self.Gamma_f = self.Gamma if spec.Gamma_f is None else np.asarray(spec.Gamma_f, float)
        self.nh = system.nh  # general path constraints h(x, u) <= 0, l1-relaxed
        self.Gamma_h = np.asarray(system.Gamma_h if spec.Gamma_h is None else spec.Gamma_h, float)
        self.Sh = np.asarray(system.h_scale, float) if self.nh else np.zeros(0)
        self._slack_scale = np.concatenate([self.Sx, self.Sh])
        if cost_scale is None:
            cost_scale = float(np.sum(system.Q * self.Sx**2) + np.sum(system.R * self.Su**2)) / (
                self.nx + self.nu
            )
        self.cost_scale = float(cost_scale)
        self._linsol = linsol
        self._codegen = bool(codegen)
        self._build()
        cold, warm = _ipopt_options(
            tol, self.tau, max_iter, options=solver_options, warm=warm_options
        )
        nlp: dict | str = self._nlp
        #: how the MPC's functions were built: {"codegen", and with it "path", "cached", "seconds"}
        self.build_info: dict = {"codegen": self._codegen}
        if self._codegen:
            lib = self._compiled_library(cache_dir)
            nlp = str(lib)
            self._sens = ca.external("sens", str(lib))
            self._newton_fn = ca.external("newton", str(lib))
        # the functions of the Newton steps and the sensitivities, called on numpy buffers (the
        # same numbers, without a DM per argument)
        self._newton_call = _NumpyCall(self._newton_fn)
        self._sens_call = _NumpyCall(self._sens)
        self._solver = ca.nlpsol("mpc", "ipopt", nlp, cold)
        self._solver_warm: ca.Function | None = (
            ca.nlpsol("mpc_warm", "ipopt", nlp, warm) if self.warm_start else None
        )
        self._prev: dict | None = None

    # ------------------------------------------------------------------ construction
    def _build(self) -> None:
        """The NLP of eq. (V0) in the scaled variables, its warm-start shifts and KKT system."""
        x0 = ca.SX.sym("x0", self.nx)
        th = ca.SX.sym("theta", self.n_theta)
        wv, geq, gin, f = self._transcribe(x0, th)
        p = ca.vertcat(x0, th)
        self.nw, self.neq, self.nin = wv.numel(), geq.numel(), gin.numel()
        self._lbg = np.concatenate([np.zeros(self.neq), np.full(self.nin, -np.inf)])
        self._ubg = np.zeros(self.neq + self.nin)
        self._nlp = {"x": wv, "p": p, "f": f, "g": ca.vertcat(geq, gin)}
        self._iu_flat = np.array(sum(self._iu, []))
        self._ix_flat = np.array(sum(self._ix, []))
        self._ie_flat = np.array(sum(self._ie, []))
        self._wshift, self._gshift = self._shift_maps()
        self._kkt_functions(wv, geq, gin, f, th, p)

    def _theta_terms(self, th: ca.SX) -> _ThetaTerms:
        """The blocks of theta as the cost weights, model parameters and bounds they set."""
        sysm, P, nx = self.system, self.param, self.nx
        b = P.blocks
        theta_c = th[b["theta_c"]][0]
        Tw, G, Qw, Rw = th[b["T"]], th[b["G"]], th[b["Q"]], th[b["R"]]
        pm = ca.SX(ca.DM(self.model_params))
        if "model" in b:  # learnable model parameters (eq. mpc_model with f_hat_theta)
            mth = th[b["model"]]
            for j, idx in enumerate(P.model_param_index):
                pm[idx] = mth[j]
        if sysm.mpc_spec.full_weights:  # W = L L^T from the Cholesky entries
            Tw, Qw = weight_matrix(Tw, nx), weight_matrix(Qw, nx)
            Rw = weight_matrix(Rw, self.nu)
        x_lo, x_hi = ca.SX(ca.DM(sysm.x_lb)), ca.SX(ca.DM(sysm.x_ub))
        if "backoff" in b:  # constraint back-offs b_lb, b_ub (eq. violation)
            bo = th[b["backoff"]]
            x_lo, x_hi = x_lo + bo[:nx], x_hi - bo[nx:]
        return _ThetaTerms(theta_c, Tw, G, Qw, Rw, pm, x_lo, x_hi)

    def _transcribe(self, x0: ca.SX, th: ca.SX) -> tuple[ca.SX, ca.SX, ca.SX, ca.SX]:
        """Multiple shooting of eq. (V0) over stages 0..N: (w, G, H, cost / cost_scale).

        Sets the bounds of ``w`` and the index lists of its inputs, states and slacks.
        """
        sysm, nx, N = self.system, self.nx, self.N
        Sx, Su, xr, ur = self.Sx, self.Su, sysm.x_ref, sysm.u_ref
        t = self._theta_terms(th)
        F = sysm.discrete_step
        w = _Decisions()
        self._iu: list[int] = []  # index lists into w
        self._ix: list[int] = []
        self._ie: list[int] = []
        zu_lb, zu_ub = (sysm.u_lb - ur) / Su, (sysm.u_ub - ur) / Su
        g_eq, g_in = [], []
        cost = t.theta_c
        x_phys = x0
        nh = self.nh
        for i in range(N + 1):
            ze = w.add(f"eta{i}", [0.0] * (nx + nh), [np.inf] * (nx + nh), self._ie)  # eq. slack
            eta, eta_h = (Sx * ze[:nx], self.Sh * ze[nx:]) if nh else (Sx * ze, None)
            g_in += self._state_rows(x_phys, eta, t)
            dx = x_phys - xr
            if i < N:
                zu = w.add(f"u{i}", list(zu_lb), list(zu_ub), self._iu)
                u_phys = ur + Su * zu
                du = u_phys - ur
                gi = self.gamma**i
                cost += gi * (_quad(dx, t.Q) + _quad(du, t.R) + ca.dot(self.Gamma, eta))
                cost += ca.dot(t.G, ca.vertcat(dx, du))
            if nh:  # h(x_i, u_i) <= eta^h_i; at stage N with the last input
                h = sysm.path_function(x_phys, u_phys)  # type: ignore[misc]  # nh > 0: set
                g_in += [(h[j] - eta_h[j]) / self.Sh[j] for j in range(nh)]  # type: ignore[index]
                cost += (gi if i < N else self.gamma**N) * ca.dot(self.Gamma_h, eta_h)  # type: ignore[arg-type]
            if i < N:
                zx = w.add(f"x{i + 1}", [-np.inf] * nx, [np.inf] * nx, self._ix)
                x_next = xr + Sx * zx
                g_eq.append((F(x_phys, u_phys, t.pm) - x_next) / Sx)  # (eq. mpc_model)
                x_phys = x_next
            else:
                cost += ca.dot(t.G[:nx], dx)
                cost += self.gamma**N * (_quad(dx, t.T) + ca.dot(self.Gamma_f, eta))
        self._lbw, self._ubw = np.array(w.lb), np.array(w.ub)
        return ca.vertcat(*w.w), ca.vertcat(*g_eq), ca.vertcat(*g_in), cost / self.cost_scale

    def _state_rows(self, x_phys: ca.SX, eta: ca.SX | np.ndarray, t: _ThetaTerms) -> list:
        """l1-relaxed state constraints of one stage (eq. violation), scaled rows ``H <= 0``."""
        sysm, Sx = self.system, self.Sx
        rows = []
        for j in range(self.nx):
            if np.isfinite(sysm.x_lb[j]):
                rows.append((t.x_lo[j] - x_phys[j] - eta[j]) / Sx[j])
            if np.isfinite(sysm.x_ub[j]):
                rows.append((x_phys[j] - t.x_hi[j] - eta[j]) / Sx[j])
        return rows

    def _shift_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """One-stage shift of ``w`` and of the constraint rows (the last stage is repeated)."""
        N, nx = self.N, self.nx
        wshift = np.arange(self.nw)
        for lst in (self._iu, self._ix, self._ie):
            for i in range(len(lst) - 1):
                wshift[lst[i]] = lst[i + 1]
        m = self.nin // (N + 1)  # inequality rows per stage
        eq_rows = np.arange(self.neq).reshape(N, nx)
        in_rows = self.neq + np.arange(self.nin).reshape(N + 1, m)
        gshift = np.concatenate(
            [
                np.vstack([eq_rows[1:], eq_rows[-1:]]).reshape(-1),
                np.vstack([in_rows[1:], in_rows[-1:]]).reshape(-1),
            ]
        )
        return wshift, gshift

    def _kkt_functions(
        self, wv: ca.SX, geq: ca.SX, gin: ca.SX, f: ca.SX, th: ca.SX, p: ca.SX
    ) -> None:
        """The barrier-relaxed KKT residual R(y, p) and its Jacobians (eq. nabla_pi).

        Sets ``_kkt`` = (w, lam, mu, p) -> (dR/dy, dR/dtheta, df/dtheta, df/dw) and the
        sensitivity function ``_sens`` built on it.
        """
        lb_idx = np.flatnonzero(np.isfinite(self._lbw))
        ub_idx = np.flatnonzero(np.isfinite(self._ubw))
        self._lb_idx, self._ub_idx = lb_idx, ub_idx
        H = ca.vertcat(
            gin,
            ca.DM(self._lbw[lb_idx]) - wv[lb_idx.tolist()],
            wv[ub_idx.tolist()] - ca.DM(self._ubw[ub_idx]),
        )
        self.nH = H.numel()
        lam = ca.SX.sym("lam", self.neq)
        mu = ca.SX.sym("mu", self.nH)
        lagr = f + ca.dot(lam, geq) + ca.dot(mu, H)
        grad_lagr = ca.gradient(lagr, wv)
        R = ca.vertcat(grad_lagr, geq, mu * H + self.tau)
        y = ca.vertcat(wv, lam, mu)
        Jy = ca.jacobian(R, y)
        Jth = ca.jacobian(R, th)
        # total derivative of the returned value f(w*(theta), theta): partial in theta plus
        # grad_w f . dw/dtheta. It equals dLagr/dtheta up to O(tau) terms and is exact for the
        # barrier solution the solver returns.
        dfdth = ca.gradient(f, th)
        dfdw = ca.gradient(f, wv)
        self._kkt = ca.Function("kkt", [wv, lam, mu, p], [Jy, Jth, dfdth, dfdw])
        self._ny = y.numel()
        self._sens = self._sensitivity_function(self._linsol)
        self._newton_fn = self._newton_function(wv, y, p, R, Jy, H, f)

    def _newton_function(
        self,
        wv: ca.SX,
        y: ca.SX,
        p: ca.SX,
        R: ca.SX,
        Jy: ca.SX,
        H: ca.SX,
        f: ca.SX,
    ) -> ca.Function:
        """(y, p) -> (y+ = y + a dy, |R(y)|_inf, |R(y+)|_inf, f(y+), max H(y+), min mu+): one
        Newton step on the barrier KKT system, ``dR/dy dy = -R``, with the fraction-to-boundary
        rule ``a <= 1``: ``mu + a dmu`` and (to first order) ``H + a dH`` keep 0.5 % of their
        distance to 0; and the residual at the new point, so that no step is taken in vain."""
        nw, neq = self.nw, self.neq
        dw = ca.SX.sym("dw", self.nw)
        res = ca.Function("newton_res", [y, p], [R, Jy, H])
        point = ca.Function("newton_point", [y, p], [ca.norm_inf(R), f, ca.mmax(H)])
        dH = ca.Function("newton_dH", [wv, p, dw], [ca.jtimes(H, wv, dw)])
        Y = ca.MX.sym("y", self._ny)
        P = ca.MX.sym("p", p.numel())
        Rv, J, Hv = res(Y, P)
        dy = ca.solve(J, -Rv, self._linsol)
        a = _fraction_to_boundary(Y[nw + neq :], dy[nw + neq :], Hv, dH(Y[:nw], P, dy[:nw]))
        Y1 = Y + a * dy
        res1, f1, h1 = point(Y1, P)
        out = [Y1, ca.norm_inf(Rv), res1, f1, h1, ca.mmin(Y1[nw + neq :]), ca.mmax(Hv)]
        return ca.Function("newton", [Y, P], out)

    def _sensitivity_function(self, linsol: str) -> ca.Function:
        """(w, lam, mu, p) -> (dpi/dtheta, dV/dtheta), one call, one sparse factorisation.

        Adjoint form: with ``dy/dtheta = -(dR/dy)^-1 dR/dtheta``, only ``nu + 1`` linear
        functionals of ``dy`` are needed (the first input and ``grad_w f . dw``), so one solve
        with the transposed KKT matrix and ``nu + 1`` right-hand sides gives both gradients.
        """
        nu, n_th = self.nu, self.n_theta
        w = ca.MX.sym("w", self.nw)
        lam = ca.MX.sym("lam", self.neq)
        mu = ca.MX.sym("mu", self.nH)
        p = ca.MX.sym("p", self.nx + n_th)
        Jy, Jth, dfdth, dfdw = self._kkt(w, lam, mu, p)
        E = np.zeros((self._ny, nu))
        E[self._iu[0], np.arange(nu)] = self.Su
        B = ca.horzcat(ca.DM(E), ca.vertcat(dfdw, ca.DM.zeros(self._ny - self.nw)))
        L = ca.solve(Jy.T, B, linsol)
        dpi = -ca.mtimes(Jth.T, L[:, :nu])  # (eq. nabla_pi), physical, (n_theta, nu)
        dV = self.cost_scale * (dfdth - ca.mtimes(Jth.T, L[:, nu]))
        return ca.Function("sens", [w, lam, mu, p], [dpi, dV])

    def _compiled_library(self, cache_dir: str | os.PathLike | None) -> Path:
        """The NLP functions IPOPT calls, ``_sens`` and ``_newton_fn``, compiled (or loaded from
        the cache)."""
        nlp = ca.Function(
            "nlp",
            [self._nlp["x"], self._nlp["p"]],
            [self._nlp["f"], self._nlp["g"]],
            ["x", "p"],
            ["f", "g"],
        )
        probe = ca.nlpsol("probe", "ipopt", self._nlp, {"calc_lam_p": True})
        names = ("nlp_f", "nlp_g", "nlp_grad_f", "nlp_jac_g", "nlp_hess_l", "nlp_grad")
        functions = [nlp, *(probe.get_function(n) for n in names), self._sens, self._newton_fn]
        return compiled_library(functions, directory=cache_dir, info=self.build_info)

    # ------------------------------------------------------------------ validation
    def check_theta(self, theta: ArrayLike | None) -> np.ndarray:
        """``theta`` as a float vector of length ``n_theta`` (None: theta0); a wrong shape or a
        non-finite value is a ``ValueError``."""
        if theta is None:
            return self.theta0.copy()
        theta = np.asarray(theta, dtype=float)
        if theta.ndim != 1 or theta.shape[0] != self.n_theta:
            raise ValueError(
                f"theta has shape {theta.shape}, expected ({self.n_theta},): {self.theta_names}"
            )
        if not np.all(np.isfinite(theta)):
            raise ValueError(f"theta contains NaN or inf: {theta}")
        return theta

    def reset(self) -> None:
        """Forget the warm start (call between episodes)."""
        self._prev = None

    # ------------------------------------------------------------------ solve
    def _cold_guess(self, x: np.ndarray) -> np.ndarray:
        w0 = np.zeros(self.nw)
        zx0 = (x - self.system.x_ref) / self.Sx
        for idx in self._ix:
            w0[idx] = zx0
        return w0

    def fallback_action(self) -> np.ndarray:
        """The safe input used when a solve fails: the shifted previous plan, else ``u_r``."""
        if self._prev is not None and self._prev["plan_u"] is not None:
            plan = self._prev["plan_u"]
            age = min(self._prev["age"] + 1, plan.shape[0] - 1)
            return self.system.clip_input(plan[age])
        return self.system.clip_input(self.system.u_ref)

    def solve(
        self, x: ArrayLike, theta: ArrayLike | None = None, sensitivities: bool = True
    ) -> MPCSolution:
        """Solve eq. (V0) at state ``x``; return pi_theta(x), V_theta(x) and their gradients."""
        x = self.system.check_state(x)
        theta = self.check_theta(theta)
        t0 = time.perf_counter()
        p = np.concatenate([x, theta])
        warm = self.warm_start and self._prev is not None
        if warm and self._newton:
            found = self._newton_solve(p)
            if found is not None:
                sol = self._solution(x, p, *found, sensitivities=sensitivities)
                sol.solve_time = time.perf_counter() - t0
                return sol
        ok, status, iters, out, wopt = self._run_solver(x, p, warm)
        if not ok and warm:  # a warm start can mislead IPOPT: retry once from a cold start
            ok, status, iters2, out, wopt = self._run_solver(x, p, False)
            iters += iters2
        if not ok:
            sol = self._failed_solution(status, iters, sensitivities)
        else:
            sol = self._solution(x, p, out, wopt, status, iters, sensitivities=sensitivities)
        sol.solve_time = time.perf_counter() - t0
        return sol

    def _failed_solution(self, status: str, iters: int, sensitivities: bool) -> MPCSolution:
        """The fallback input (the previous plan, one step older) and NaN value and gradients."""
        act = self.fallback_action()
        if self._prev is not None:
            self._prev["age"] += 1
        nan = np.full(self.n_theta, np.nan)
        return MPCSolution(
            action=act,
            value=np.nan,
            dpi_dtheta=np.full((self.n_theta, self.nu), np.nan) if sensitivities else None,
            dV_dtheta=nan if sensitivities else None,
            success=False,
            status=status,
            slack=np.nan,
            iterations=iters,
            fallback=True,
        )

    def _solution(
        self,
        x: np.ndarray,
        p: np.ndarray,
        out: dict[str, ca.DM],
        wopt: np.ndarray,
        status: str,
        iters: int,
        mult: tuple[np.ndarray, np.ndarray] | None = None,
        sensitivities: bool = True,
    ) -> MPCSolution:
        """pi_theta(x) (eq. Policy), V_theta(x), the plan and, if asked, the sensitivities;
        the solution, shifted, is the next warm start."""
        lam_g = np.asarray(out["lam_g"]).reshape(-1)
        lam_x = np.asarray(out["lam_x"]).reshape(-1)
        plan_u = self.system.u_ref + self.Su * wopt[self._iu_flat].reshape(self.N, self.nu)
        plan_x = np.vstack(
            [x, self.system.x_ref + self.Sx * wopt[self._ix_flat].reshape(self.N, self.nx)]
        )
        slack = float(np.sum(np.tile(self._slack_scale, self.N + 1) * wopt[self._ie_flat]))
        value = float(out["f"]) * self.cost_scale
        action = self.system.clip_input(plan_u[0])
        sol = MPCSolution(
            action=action,
            value=value,
            dpi_dtheta=None,
            dV_dtheta=None,
            success=True,
            status=status,
            slack=slack,
            iterations=iters,
            plan_u=plan_u,
            plan_x=plan_x,
        )
        if sensitivities:
            try:
                sol.dpi_dtheta, sol.dV_dtheta = self._sensitivities(wopt, lam_g, lam_x, p, mult)
            except (RuntimeError, ValueError) as err:  # singular KKT matrix
                sol.dpi_dtheta = np.full((self.n_theta, self.nu), np.nan)
                sol.dV_dtheta = np.full(self.n_theta, np.nan)
                sol.info["sensitivity_error"] = str(err)
        self._remember(wopt, lam_g, lam_x, plan_u)
        return sol

    def _newton_solve(
        self, p: np.ndarray
    ) -> tuple[dict, np.ndarray, str, int, tuple[np.ndarray, np.ndarray]] | None:
        """Newton steps on R(y, p) = 0 from the shifted previous solution (``newton_steps``).

        Returns the arguments of ``_solution`` (CasADi-style outputs, w, status, steps, and the
        multipliers (lambda, mu)) when ``|R|_inf <= tol`` at a point with ``H < 0``, ``mu > 0``;
        None when the steps do not get there (IPOPT then solves)."""
        prev = self._prev
        if prev is None:
            return None
        w = prev["w_shift"]
        lam, mu = self._multipliers(w, prev["lam_g"], prev["lam_x"])
        y = np.concatenate([w, lam, mu])
        if not np.all(mu > 0):
            return None
        for k in range(1, self._newton + 1):
            y_next, *scalars = self._newton_call(y, p)
            res0, res, f, h_max, mu_min, h0_max = (float(v) for v in scalars)
            # not interior (the new state violates a row of the old plan), not converging
            # (from the 2nd step on, the residual must fall tenfold per step), or out of steps
            if not (h0_max < 0 and h_max < 0 and mu_min > 0 and np.isfinite(res)):
                return None
            y = np.asarray(y_next).reshape(-1)
            if res <= self._tol:
                break
            if k == self._newton or (k >= 2 and res > 0.1 * res0):
                return None
        return self._newton_result(y, f, "Newton_Succeeded", k)

    def _newton_result(
        self, y: np.ndarray, f: float, status: str, steps: int
    ) -> tuple[dict, np.ndarray, str, int, tuple[np.ndarray, np.ndarray]]:
        """The arguments of ``_solution`` for a root y = (w, lambda, mu) of R(y, p)."""
        nw, neq = self.nw, self.neq
        w, lam, mu = y[:nw], y[nw : nw + neq], y[nw + neq :]
        mu_g, n_lb = mu[: self.nin], len(self._lb_idx)
        lam_x = np.zeros(nw)
        lam_x[self._ub_idx] += mu[self.nin + n_lb :]
        lam_x[self._lb_idx] -= mu[self.nin : self.nin + n_lb]
        out = {"lam_g": np.concatenate([lam, mu_g]), "lam_x": lam_x, "f": f}
        return out, w, status, steps, (lam, mu)

    def _run_solver(
        self, x: np.ndarray, p: np.ndarray, warm: bool
    ) -> tuple[bool, str, int, Any, Any]:  # (ok, status, iterations, solver output, w)
        if warm:
            w0, lam_g0, lam_x0 = self._prev["w_shift"], self._prev["lam_g"], self._prev["lam_x"]  # type: ignore[index]  # warm: _prev is set
        else:
            w0, lam_g0, lam_x0 = self._cold_guess(x), None, None
        args = {
            "x0": w0,
            "p": p,
            "lbx": self._lbw,
            "ubx": self._ubw,
            "lbg": self._lbg,
            "ubg": self._ubg,
        }
        if lam_g0 is not None:
            args["lam_g0"], args["lam_x0"] = lam_g0, lam_x0
        solver: ca.Function = self._solver_warm if warm else self._solver  # type: ignore[assignment]  # warm: built
        try:
            out = solver(**args)
        except RuntimeError as err:  # IPOPT can raise on evaluation errors
            return False, f"Exception: {err}", 0, None, None
        st = solver.stats()
        status, iters = st.get("return_status", "unknown"), int(st.get("iter_count", 0))
        wopt = np.asarray(out["x"]).reshape(-1)
        ok = status in _SUCCESS and bool(np.all(np.isfinite(wopt)))
        return ok, status, iters, out, wopt

    def _remember(
        self, w: np.ndarray, lam_g: np.ndarray, lam_x: np.ndarray, plan_u: np.ndarray | None
    ) -> None:
        """Store the solution and its multipliers, shifted by one stage, as the next warm start."""
        self._prev = {
            "w_shift": w[self._wshift],
            "lam_g": lam_g[self._gshift],
            "lam_x": lam_x[self._wshift],
            "plan_u": plan_u,
            "age": 0,
        }

    def _multipliers(
        self, w: np.ndarray, lam_g: np.ndarray, lam_x: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Split CasADi's multipliers into (lambda for G, mu >= 0 for every row of H)."""
        tau = self.tau
        lam = lam_g[: self.neq]
        mu_g = np.maximum(lam_g[self.neq :], 1e-300)
        # casadi: lam_x = z_U - z_L. With both bounds finite, the far bound's multiplier follows
        # from barrier complementarity, z * gap = tau; the near one from the difference.
        gap_l = w - self._lbw
        gap_u = self._ubw - w
        zL = np.maximum(-lam_x, 0.0)
        zU = np.maximum(lam_x, 0.0)
        both = np.isfinite(gap_l) & np.isfinite(gap_u)
        near_l = both & (gap_l <= gap_u)
        near_u = both & ~near_l
        zU = np.where(near_l, tau / np.maximum(gap_u, 1e-300), zU)
        zL = np.where(near_l, zU - lam_x, zL)
        zL = np.where(near_u, tau / np.maximum(gap_l, 1e-300), zL)
        zU = np.where(near_u, lam_x + zL, zU)
        mu = np.concatenate(
            [mu_g, np.maximum(zL[self._lb_idx], 1e-300), np.maximum(zU[self._ub_idx], 1e-300)]
        )
        return lam, mu

    def _sensitivities(
        self,
        w: np.ndarray,
        lam_g: np.ndarray,
        lam_x: np.ndarray,
        p: np.ndarray,
        mult: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> tuple[np.ndarray, np.ndarray]:
        """(dpi/dtheta, dV/dtheta) at a solution (eq. nabla_pi, grad V); ``mult``: its
        (lambda, mu) when known (Newton), else recovered from CasADi's multipliers."""
        lam, mu = self._multipliers(w, lam_g, lam_x) if mult is None else mult
        dpi, dV = self._sens_call(w, lam, mu, p)
        dpi, dV = np.asarray(dpi), np.asarray(dV).reshape(-1)
        if not (np.all(np.isfinite(dpi)) and np.all(np.isfinite(dV))):
            raise ValueError("non-finite sensitivity (singular KKT matrix)")
        return dpi, dV


class _ThetaTerms(NamedTuple):
    """The symbolic pieces of eq. (V0) that theta sets."""

    theta_c: ca.SX  # constant cost offset
    T: ca.SX  # terminal weights (nx,)
    G: ca.SX  # linear cost terms (nx + nu,)
    Q: ca.SX  # stage state weights (nx,)
    R: ca.SX  # stage input weights (nu,)
    pm: ca.SX  # model parameters of f_hat_theta, the learnable ones from theta
    x_lo: ca.SX  # state bounds with the back-offs
    x_hi: ca.SX


@dataclass
class _Decisions:
    """The decision vector w of the NLP as it is built: symbols and their bounds, in order."""

    w: list = field(default_factory=list)
    lb: list = field(default_factory=list)
    ub: list = field(default_factory=list)

    def add(self, name: str, lb: list, ub: list, index: list) -> ca.SX:
        """A new block of ``len(lb)`` variables; its positions in w are appended to ``index``."""
        z = ca.SX.sym(name, len(lb))
        index.append(list(range(len(self.lb), len(self.lb) + len(lb))))
        self.w.append(z)
        self.lb += lb
        self.ub += ub
        return z


def _quad(d: Any, W: Any) -> Any:
    """``d^T W d``: ``W`` a vector of diagonal weights or a full matrix."""
    if W.shape[1] == 1:
        return ca.dot(d, W * d)
    return ca.dot(d, ca.mtimes(W, d))


def _check_options(horizon: int, gamma: float, tau: float, linsol: str) -> None:
    if horizon < 1:
        raise ValueError(f"horizon must be at least 1, got {horizon}")
    if not 0 < gamma <= 1:
        raise ValueError(f"gamma must be in (0, 1], got {gamma}")
    if tau <= 0:
        raise ValueError(f"tau must be positive, got {tau}")
    if not ca.has_linsol(linsol):
        raise ValueError(f"linsol '{linsol}' is not a linear solver plugin of this CasADi")


def _ipopt_options(
    tol: float,
    tau: float,
    max_iter: int,
    *,
    options: dict | None = None,
    warm: dict | None = None,
) -> tuple[dict, dict]:
    """CasADi ``nlpsol`` options of the cold and of the warm-started IPOPT solver.

    IPOPT stops at the barrier parameter ``tau`` (``mu_target``, the point that eq. nabla_pi
    differentiates). ``options`` go to both solvers, then ``warm`` to the warm one only, after its
    warm-start settings; a key is an IPOPT option (``"max_iter"`` or ``"ipopt.max_iter"``) unless
    it is one of CasADi's own (``"print_time"``, ``"show_eval_warnings"``).
    """
    cold = {
        "ipopt.print_level": 0,
        "print_time": False,
        # lam_p (the multipliers of the parameters) costs one more gradient evaluation per
        # solve and is not used: the sensitivities come from the KKT system
        "calc_lam_p": False,
        # IPOPT may probe wild iterates (Inf/NaN in the model, see NOTES): it backtracks by
        # itself, and a failed solve is reported in MPCSolution, so CasADi's per-evaluation
        # warnings on stderr are only noise that would bury the progress bars
        "show_eval_warnings": False,
        "ipopt.sb": "yes",
        "ipopt.tol": tol,
        "ipopt.acceptable_tol": max(1e-6, 100 * tol),
        "ipopt.mu_target": tau,
        "ipopt.max_iter": max_iter,
        "ipopt.bound_relax_factor": 0.0,
        "ipopt.honor_original_bounds": "no",
        "ipopt.nlp_scaling_method": "none",
    }
    cold.update(_casadi_keys(options))
    warm_opts = {
        **cold,
        "ipopt.warm_start_init_point": "yes",
        "ipopt.warm_start_bound_push": 1e-6,
        "ipopt.warm_start_mult_bound_push": 1e-6,
        "ipopt.mu_init": 1e-3,
        "ipopt.max_iter": min(max_iter, 50),
    }
    warm_opts.update(_casadi_keys(warm))
    return cold, warm_opts


def _casadi_keys(options: dict | None) -> dict:
    """User solver options with IPOPT's keys prefixed ``ipopt.`` as CasADi expects."""
    own = _CASADI_NLPSOL_KEYS
    return {
        k if k.startswith("ipopt.") or k in own else f"ipopt.{k}": v
        for k, v in (options or {}).items()
    }
