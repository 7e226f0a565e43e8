"""The transcription of eq. (V0): the MPC's optimal control problem as an NLP in scaled variables.

The problem, with the cost of section 5 of the paper::

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
Cholesky entries in theta; otherwise diagonal as written above. The linear term ``G`` acts on
deviations from the reference (the paper writes it on ``[x, u]``; the two differ by a constant,
so the policy is the same and the value is better scaled).

Multiple shooting over the stages 0..N: the decision variables are scaled, ``x = x_r + S_x z_x``,
``u = u_r + S_u z_u``, ``eta = S_x z_eta``, and the cost is divided by ``cost_scale``. The
constraints are ``G(w, p) = 0`` (the model) and ``H(w, p) <= 0`` (the relaxed state bounds and
path constraints), with ``p = (x, theta)``. :class:`Transcription` also holds the layout of the
decision vector ``w``, its one-stage shift (the warm start) and the decoding of a solution into
the physical plan.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import casadi as ca
import numpy as np

from mpcmobo.systems.base import System
from mpcmobo.systems.parameterization import Parameterization, weight_matrix


class ThetaTerms(NamedTuple):
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


class Transcription:
    """Multiple shooting of eq. (V0) for one system, model, horizon and discount.

    Built once. Symbols: ``w`` (decision vector), ``theta``, ``p = (x0, theta)``, the constraint
    blocks ``geq`` (``G = 0``) and ``gin`` (``H <= 0``), the scaled cost ``f``, and ``nlp``, the
    dictionary CasADi's ``nlpsol`` takes (``g = [geq; gin]``). Numbers: the bounds ``lbw``,
    ``ubw`` of ``w`` and ``lbg``, ``ubg`` of ``g``; the positions in ``w`` of the inputs ``iu``,
    predicted states ``ix`` and slacks ``ie`` (one list per stage; ``*_flat``: all of them);
    the sizes ``nw``, ``neq``, ``nin``; the one-stage shifts ``wshift`` of ``w`` and ``gshift``
    of ``g``; the scales ``Sx``, ``Su``, ``Sh``, the l1 weights ``Gamma``, ``Gamma_f``,
    ``Gamma_h`` and ``cost_scale`` (default: the mean of the reference weights ``Q``, ``R`` in
    scaled units).
    """

    def __init__(
        self,
        system: System,
        model_params: np.ndarray,
        param: Parameterization,
        *,
        horizon: int,
        gamma: float,
        cost_scale: float | None = None,
    ) -> None:
        spec = system.mpc_spec
        self.system, self.model_params, self.param = system, model_params, param
        self.N, self.gamma = horizon, gamma
        self.nx, self.nu, self.n_theta = system.nx, system.nu, param.n_theta
        self.Sx, self.Su = np.asarray(system.x_scale, float), np.asarray(system.u_scale, float)
        self.Gamma = np.full(self.nx, 1e5) if spec.Gamma is None else np.asarray(spec.Gamma, float)
        self.Gamma_f = self.Gamma if spec.Gamma_f is None else np.asarray(spec.Gamma_f, float)
        self.nh = system.nh  # general path constraints h(x, u) <= 0, l1-relaxed
        self.Gamma_h = np.asarray(system.Gamma_h if spec.Gamma_h is None else spec.Gamma_h, float)
        self.Sh = np.asarray(system.h_scale, float) if self.nh else np.zeros(0)
        self.slack_scale = np.concatenate([self.Sx, self.Sh])
        if cost_scale is None:
            cost_scale = float(np.sum(system.Q * self.Sx**2) + np.sum(system.R * self.Su**2)) / (
                self.nx + self.nu
            )
        self.cost_scale = float(cost_scale)
        x0 = ca.SX.sym("x0", self.nx)
        self.theta = ca.SX.sym("theta", self.n_theta)
        self.w, self.geq, self.gin, self.f = self.transcribe(x0, self.theta)
        self.p = ca.vertcat(x0, self.theta)
        self.nw, self.neq, self.nin = self.w.numel(), self.geq.numel(), self.gin.numel()
        self.lbg = np.concatenate([np.zeros(self.neq), np.full(self.nin, -np.inf)])
        self.ubg = np.zeros(self.neq + self.nin)
        self.nlp = {"x": self.w, "p": self.p, "f": self.f, "g": ca.vertcat(self.geq, self.gin)}
        self.iu_flat = np.array(sum(self.iu, []))
        self.ix_flat = np.array(sum(self.ix, []))
        self.ie_flat = np.array(sum(self.ie, []))
        self.wshift, self.gshift = self._shift_maps()

    def theta_terms(self, th: ca.SX) -> ThetaTerms:
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
        return ThetaTerms(theta_c, Tw, G, Qw, Rw, pm, x_lo, x_hi)

    def transcribe(self, x0: ca.SX, th: ca.SX) -> tuple[ca.SX, ca.SX, ca.SX, ca.SX]:
        """Multiple shooting of eq. (V0) over stages 0..N: (w, G, H, cost / cost_scale).

        Sets the bounds ``lbw``, ``ubw`` of ``w`` and the index lists ``iu``, ``ix``, ``ie`` of
        its inputs, states and slacks (the same for every call: the layout does not depend on
        the symbols).
        """
        sysm, nx, N = self.system, self.nx, self.N
        Sx, Su, xr, ur = self.Sx, self.Su, sysm.x_ref, sysm.u_ref
        t = self.theta_terms(th)
        F = sysm.discrete_step
        w = _Decisions()
        self.iu: list[list[int]] = []  # index lists into w, one per stage
        self.ix: list[list[int]] = []
        self.ie: list[list[int]] = []
        zu_lb, zu_ub = (sysm.u_lb - ur) / Su, (sysm.u_ub - ur) / Su
        g_eq, g_in = [], []
        cost = t.theta_c
        x_phys = x0
        nh = self.nh
        for i in range(N + 1):
            ze = w.add(f"eta{i}", [0.0] * (nx + nh), [np.inf] * (nx + nh), self.ie)  # eq. slack
            eta, eta_h = (Sx * ze[:nx], self.Sh * ze[nx:]) if nh else (Sx * ze, None)
            g_in += self._state_rows(x_phys, eta, t)
            dx = x_phys - xr
            if i < N:
                zu = w.add(f"u{i}", list(zu_lb), list(zu_ub), self.iu)
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
                zx = w.add(f"x{i + 1}", [-np.inf] * nx, [np.inf] * nx, self.ix)
                x_next = xr + Sx * zx
                g_eq.append((F(x_phys, u_phys, t.pm) - x_next) / Sx)  # (eq. mpc_model)
                x_phys = x_next
            else:
                cost += ca.dot(t.G[:nx], dx)
                cost += self.gamma**N * (_quad(dx, t.T) + ca.dot(self.Gamma_f, eta))
        self.lbw, self.ubw = np.array(w.lb), np.array(w.ub)
        return ca.vertcat(*w.w), ca.vertcat(*g_eq), ca.vertcat(*g_in), cost / self.cost_scale

    def _state_rows(self, x_phys: ca.SX, eta: ca.SX | np.ndarray, t: ThetaTerms) -> list:
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
        for lst in (self.iu, self.ix, self.ie):
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

    def cold_guess(self, x: np.ndarray) -> np.ndarray:
        """The initial guess without a warm start: every predicted state at ``x``, every input
        at ``u_r``, every slack 0."""
        w0 = np.zeros(self.nw)
        zx0 = (x - self.system.x_ref) / self.Sx
        for idx in self.ix:
            w0[idx] = zx0
        return w0

    def plan(self, x: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
        """The physical plan of a solution ``w`` from state ``x``: the inputs (N, nu), the
        states (N+1, nx) and the sum of the slacks (physical units)."""
        sysm, N = self.system, self.N
        plan_u = sysm.u_ref + self.Su * w[self.iu_flat].reshape(N, self.nu)
        plan_x = np.vstack([x, sysm.x_ref + self.Sx * w[self.ix_flat].reshape(N, self.nx)])
        slack = float(np.sum(np.tile(self.slack_scale, N + 1) * w[self.ie_flat]))
        return plan_u, plan_x, slack

    def shifted(
        self, w: np.ndarray, lam_g: np.ndarray, lam_x: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """A solution and its multipliers one stage later: the next solve's warm start (of
        one solution per row, too)."""
        return w[..., self.wshift], lam_g[..., self.gshift], lam_x[..., self.wshift]
