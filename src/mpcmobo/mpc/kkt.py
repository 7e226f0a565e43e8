"""The barrier-relaxed KKT residual of eq. (V0) and the functions built on it.

IPOPT is run to the barrier parameter ``tau`` (option ``mu_target``), so its solution is exactly
the root of the barrier-relaxed primal-dual KKT residual::

    R(y, p) = [ grad_zeta Lagr ;  G ;  diag(mu) H + tau ],   y = (zeta, lambda, mu),

with ``Lagr = Phi + lambda^T G + mu^T H`` and ``H <= 0`` collecting every inequality (general and
simple bounds). ``R`` is smooth across active-set changes and ``dR/dy`` stays invertible, so

    d pi / d theta = - (dR/dtheta)^T (dR/dy)^{-T} e_{u_0}                             (eq. nabla_pi)
    d V  / d theta = d Lagr / d theta at the solution                                  (grad V)

and the finite differences of the solver's own outputs agree with them. Both come from one
adjoint solve (:meth:`KKTSystem.sensitivities`). The same residual gives the Newton step of warm
solves, ``dR/dy dy = -R`` with a fraction-to-boundary rule (:mod:`mpcmobo.mpc.solve` iterates
it). The functions are CasADi functions, called on numpy buffers (:class:`NumpyCall`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import casadi as ca
import numpy as np

from mpcmobo.mpc.transcription import Transcription


class NumpyCall:
    """A CasADi function evaluated into preallocated numpy arrays: ``f(*args)`` returns its
    outputs (2-d arrays in the function's shapes, floats for scalars), the numbers of ``fn(*args)``
    bit for bit, without converting every argument and result to a ``DM`` (that conversion is
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
        """The outputs of ``fn(*values)``, as numpy arrays and floats."""
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


def fraction_to_boundary(mu: ca.MX, dmu: ca.MX, H: ca.MX, dH: ca.MX) -> ca.MX:
    """The step length ``a <= 1`` of a Newton step after which the multipliers ``mu + a dmu``
    and (to first order) the inequalities ``H + a dH`` keep 0.5 % of their distance to 0."""
    big = ca.DM(1e300)
    a_mu = ca.mmin(ca.if_else(dmu < 0, -mu / dmu, big))
    a_H = ca.mmin(ca.if_else(dH > 0, -H / dH, big))
    return ca.fmin(1.0, 0.995 * ca.fmin(a_mu, a_H))


class KKTSystem:
    """The KKT residual ``R(y, p)`` of a :class:`~mpcmobo.mpc.transcription.Transcription` at
    the barrier parameter ``tau``, and the CasADi functions built on it.

    ``H`` stacks the general inequalities ``gin`` and the finite simple bounds of ``w`` (lower:
    positions ``lb_idx``, upper: ``ub_idx``), ``nH`` rows; ``y = (w, lambda, mu)`` has ``ny``
    entries. Functions: ``kkt``: (w, lam, mu, p) -> (dR/dy, dR/dtheta, df/dtheta, df/dw);
    ``sens``: (w, lam, mu, p) -> (dpi/dtheta, dV/dtheta); ``newton``: (y, p) -> one Newton step
    (:meth:`_newton_function`). ``linsol``: the CasADi linear solver of their linear systems.
    """

    def __init__(self, problem: Transcription, tau: float, linsol: str) -> None:
        self.problem, self.tau, self.linsol = problem, float(tau), linsol
        self.nw, self.neq, self.nin = problem.nw, problem.neq, problem.nin
        wv, geq, f, th, p = problem.w, problem.geq, problem.f, problem.theta, problem.p
        lbw, ubw = problem.lbw, problem.ubw
        lb_idx = np.flatnonzero(np.isfinite(lbw))
        ub_idx = np.flatnonzero(np.isfinite(ubw))
        self.lb_idx, self.ub_idx = lb_idx, ub_idx
        H = ca.vertcat(
            problem.gin,
            ca.DM(lbw[lb_idx]) - wv[lb_idx.tolist()],
            wv[ub_idx.tolist()] - ca.DM(ubw[ub_idx]),
        )
        self.nH = H.numel()
        lam = ca.SX.sym("lam", self.neq)
        mu = ca.SX.sym("mu", self.nH)
        lagr = f + ca.dot(lam, geq) + ca.dot(mu, H)
        R = ca.vertcat(ca.gradient(lagr, wv), geq, mu * H + self.tau)
        y = ca.vertcat(wv, lam, mu)
        Jy = ca.jacobian(R, y)
        Jth = ca.jacobian(R, th)
        # total derivative of the returned value f(w*(theta), theta): partial in theta plus
        # grad_w f . dw/dtheta. It equals dLagr/dtheta up to O(tau) terms and is exact for the
        # barrier solution the solver returns.
        dfdth = ca.gradient(f, th)
        dfdw = ca.gradient(f, wv)
        self.kkt = ca.Function("kkt", [wv, lam, mu, p], [Jy, Jth, dfdth, dfdw])
        self.ny = y.numel()
        self.sens = self._sensitivity_function()
        self.newton = self._newton_function(wv, y, p, R, Jy, H, f)
        # the same step on the residual at a barrier parameter m >= tau (the interior-point
        # continuation of :mod:`mpcmobo.mpc.interior`), and the rows H(w, p) themselves
        m = ca.SX.sym("m")
        R_m = ca.vertcat(R[: self.nw + self.neq], mu * H + m)
        self.newton_mu = self._newton_function(wv, y, p, R_m, Jy, H, f, m)
        self.rows = ca.Function("rows", [wv, p], [H])
        self.reduced_hessian = _reduced_hessian_function(
            wv, y, p, lagr, geq, H, mu, problem.ix_flat, linsol
        )
        self.slack_of_row = _slack_of_row(H, wv, problem.ie_flat)
        self._wrap()

    def load(self, library: Path) -> None:
        """Use the compiled ``sens`` and ``newton`` of a library made by
        :func:`mpcmobo.mpc.codegen.compiled_library` (the same numbers, faster)."""
        self.sens = ca.external("sens", str(library))
        self.newton = ca.external("newton", str(library))
        self.newton_mu = ca.external("newton_mu", str(library))
        self.rows = ca.external("rows", str(library))
        self.reduced_hessian = ca.external("reduced_hessian", str(library))
        self._wrap()

    def _wrap(self) -> None:
        """``sens_call``, ``newton_call``: ``sens`` and ``newton`` on numpy buffers."""
        self.sens_call = NumpyCall(self.sens)
        self.newton_call = NumpyCall(self.newton)
        self.newton_mu_call = NumpyCall(self.newton_mu)
        self.rows_call = NumpyCall(self.rows)
        self.reduced_hessian_call = NumpyCall(self.reduced_hessian)

    def is_minimum(self, y: np.ndarray, p: np.ndarray) -> bool:
        """Whether the root ``y`` of ``R(., p)`` is a strict local minimum of the barrier
        problem and not a saddle point: the condensed Hessian ``K = W + A_H^T diag(mu / -H)
        A_H`` positive definite on the null space of the equalities' Jacobian, that is the
        Newton matrix's inertia that of a minimum: a Cholesky factorisation of the reduced
        Hessian (:func:`_reduced_hessian_function`) succeeds. Newton steps without a merit
        function converge to either; IPOPT's inertia correction steers to minima. The embedded
        controller runs the same function and the same factorisation."""
        M = np.asarray(self.reduced_hessian_call(y, p)[0], float)
        if not np.all(np.isfinite(M)):
            return False
        try:
            np.linalg.cholesky(M)
        except np.linalg.LinAlgError:
            return False
        return True

    def _newton_function(
        self,
        wv: ca.SX,
        y: ca.SX,
        p: ca.SX,
        R: ca.SX,
        Jy: ca.SX,
        H: ca.SX,
        f: ca.SX,
        m: ca.SX | None = None,
    ) -> ca.Function:
        """(y, p) -> (y+ = y + a dy, |R(y)|_inf, |R(y+)|_inf, f(y+), max H(y+), min mu+,
        max H(y)): one Newton step on the barrier KKT system, ``dR/dy dy = -R``, with the
        fraction-to-boundary rule ``a <= 1`` (:func:`fraction_to_boundary`); and the residual at
        the new point, so that no step is taken in vain. With ``m`` (the barrier parameter of
        ``R``, a symbol): ``newton_mu``, (y, p, m) -> the same outputs."""
        nw, neq = self.nw, self.neq
        dw = ca.SX.sym("dw", self.nw)
        extra = [] if m is None else [m]
        res = ca.Function("newton_res", [y, p, *extra], [R, Jy, H])
        point = ca.Function("newton_point", [y, p, *extra], [ca.norm_inf(R), f, ca.mmax(H)])
        dH = ca.Function("newton_dH", [wv, p, dw], [ca.jtimes(H, wv, dw)])
        Y = ca.MX.sym("y", self.ny)
        P = ca.MX.sym("p", p.numel())
        M = [] if m is None else [ca.MX.sym("m")]
        Rv, J, Hv = res(Y, P, *M)
        dy = ca.solve(J, -Rv, self.linsol)
        a = fraction_to_boundary(Y[nw + neq :], dy[nw + neq :], Hv, dH(Y[:nw], P, dy[:nw]))
        Y1 = Y + a * dy
        res1, f1, h1 = point(Y1, P, *M)
        out = [Y1, ca.norm_inf(Rv), res1, f1, h1, ca.mmin(Y1[nw + neq :]), ca.mmax(Hv)]
        return ca.Function("newton" if m is None else "newton_mu", [Y, P, *M], out)

    def _sensitivity_function(self) -> ca.Function:
        """(w, lam, mu, p) -> (dpi/dtheta, dV/dtheta), one call, one sparse factorisation.

        Adjoint form: with ``dy/dtheta = -(dR/dy)^-1 dR/dtheta``, only ``nu + 1`` linear
        functionals of ``dy`` are needed (the first input and ``grad_w f . dw``), so one solve
        with the transposed KKT matrix and ``nu + 1`` right-hand sides gives both gradients.
        """
        problem = self.problem
        nu, n_th = problem.nu, problem.n_theta
        w = ca.MX.sym("w", self.nw)
        lam = ca.MX.sym("lam", self.neq)
        mu = ca.MX.sym("mu", self.nH)
        p = ca.MX.sym("p", problem.nx + n_th)
        Jy, Jth, dfdth, dfdw = self.kkt(w, lam, mu, p)
        E = np.zeros((self.ny, nu))
        E[problem.iu[0], np.arange(nu)] = problem.Su
        B = ca.horzcat(ca.DM(E), ca.vertcat(dfdw, ca.DM.zeros(self.ny - self.nw)))
        L = ca.solve(Jy.T, B, self.linsol)
        dpi = -ca.mtimes(Jth.T, L[:, :nu])  # (eq. nabla_pi), physical, (n_theta, nu)
        dV = problem.cost_scale * (dfdth - ca.mtimes(Jth.T, L[:, nu]))
        return ca.Function("sens", [w, lam, mu, p], [dpi, dV])

    def multipliers(
        self, w: np.ndarray, lam_g: np.ndarray, lam_x: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Split CasADi's multipliers into (lambda for G, mu >= 0 for every row of H); of
        several solutions at once, one per row (a batch, :mod:`mpcmobo.mpc.batch`)."""
        tau = self.tau
        lbw, ubw = self.problem.lbw, self.problem.ubw
        lam = lam_g[..., : self.neq]
        mu_g = np.maximum(lam_g[..., self.neq :], 1e-300)
        # casadi: lam_x = z_U - z_L. With both bounds finite, the far bound's multiplier follows
        # from barrier complementarity, z * gap = tau; the near one from the difference.
        gap_l = w - lbw
        gap_u = ubw - w
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
            [
                mu_g,
                np.maximum(zL[..., self.lb_idx], 1e-300),
                np.maximum(zU[..., self.ub_idx], 1e-300),
            ],
            axis=-1,
        )
        return lam, mu

    def solver_outputs(
        self, y: np.ndarray, f: float | np.ndarray
    ) -> tuple[dict, np.ndarray, tuple[np.ndarray, np.ndarray]]:
        """A root y = (w, lambda, mu) of R as IPOPT's outputs: ({"lam_g", "lam_x", "f"}, w,
        (lambda, mu)), the inverse of :meth:`multipliers` (of one root per row, too)."""
        nw, neq = self.nw, self.neq
        w, lam, mu = y[..., :nw], y[..., nw : nw + neq], y[..., nw + neq :]
        mu_g, n_lb = mu[..., : self.nin], len(self.lb_idx)
        lam_x = np.zeros(w.shape)
        lam_x[..., self.ub_idx] += mu[..., self.nin + n_lb :]
        lam_x[..., self.lb_idx] -= mu[..., self.nin : self.nin + n_lb]
        out = {"lam_g": np.concatenate([lam, mu_g], axis=-1), "lam_x": lam_x, "f": f}
        return out, w, (lam, mu)

    def sensitivities(
        self, w: np.ndarray, lam: np.ndarray, mu: np.ndarray, p: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(dpi/dtheta (n_theta, nu), dV/dtheta (n_theta,)) at a solution (eq. nabla_pi, grad V);
        a ``ValueError`` when they are not finite (a singular KKT matrix)."""
        dpi, dV = self.sens_call(w, lam, mu, p)
        dpi, dV = np.asarray(dpi), np.asarray(dV).reshape(-1)
        if not (np.all(np.isfinite(dpi)) and np.all(np.isfinite(dV))):
            raise ValueError("non-finite sensitivity (singular KKT matrix)")
        return dpi, dV


def _reduced_hessian_function(
    wv: ca.SX,
    y: ca.SX,
    p: ca.SX,
    lagr: ca.SX,
    geq: ca.SX,
    H: ca.SX,
    mu: ca.SX,
    states: np.ndarray,
    linsol: str,
) -> ca.Function:
    """``reduced_hessian``: (y, p) -> the reduced Hessian ``Z^T K Z`` (dense): ``K = W + A_H^T
    diag(mu / -H) A_H``, the barrier Lagrangian's Hessian condensed on the inequalities, and
    ``Z`` the basis of the equalities' null space that eliminates the predicted ``states``
    (positions in ``w``) through the model's defects, ``Z_states = -A_states^{-1} A_free``
    (``A_states`` is triangular: stage by stage; solved with ``linsol``). It is positive
    definite, the root a minimum (:meth:`KKTSystem.is_minimum`), exactly when a Cholesky
    factorisation of it succeeds. K and A are expressions (SX), the elimination and the
    products matrix operations (MX), so that the generated code stays small."""
    A_H = ca.jacobian(H, wv)
    K = ca.hessian(lagr, wv)[0] + ca.mtimes([A_H.T, ca.diag(mu / -H), A_H])
    curvature = ca.Function("curvature", [y, p], [K, ca.jacobian(geq, wv)])
    nw = wv.numel()
    dep = [int(i) for i in states]
    free = sorted(set(range(nw)) - set(dep))
    Y, P = ca.MX.sym("y", y.numel()), ca.MX.sym("p", p.numel())
    K_m, A_m = curvature(Y, P)
    Z_dep = -ca.solve(A_m[:, dep], A_m[:, free], linsol)
    select_free = ca.DM(ca.Sparsity.triplet(nw, len(free), free, list(range(len(free)))), 1.0)
    select_dep = ca.DM(ca.Sparsity.triplet(nw, len(dep), dep, list(range(len(dep)))), 1.0)
    Z = select_free + ca.mtimes(select_dep, Z_dep)
    return ca.Function("reduced_hessian", [Y, P], [ca.densify(ca.mtimes([Z.T, K_m, Z]))])


def _slack_of_row(H: ca.SX, w: ca.SX, slacks: np.ndarray) -> np.ndarray:
    """For each row of ``H``, the position in ``w`` of the slack that relaxes it, or -1.

    A row relaxed by a slack ``z`` has ``dH/dz = -1`` (the transcription's rows are
    ``(... - eta) / scale`` with ``eta = scale z``): raising ``z`` by ``d`` lowers the row by
    ``d``, exactly. A row with several slacks, or none, gets -1.
    """
    J = ca.Function("dH_dslack", [w], [ca.jacobian(H, w[slacks.tolist()])])
    D = np.asarray(ca.DM(J(ca.DM.zeros(w.numel()))).full())
    rows = np.full(H.numel(), -1)
    for j in range(H.numel()):
        nz = np.flatnonzero(D[j])
        if len(nz) == 1 and D[j, nz[0]] == -1.0:
            rows[j] = slacks[nz[0]]
    return rows
