"""Least squares on the one-step prediction error of the system's model structure.

For the identified parameters ``q`` (a subset of the model parameters ``p``, the others at
their nominal values) the residual of a transition is the scaled one-step prediction error

    r_k(q) = (F(x_k, u_k, p(q)) - x_{k+1}) / x_scale,

``F`` the system's ``discrete_step`` (the same discretisation the MPC predicts with). The fit
minimises ``sum_k rho(|r_k|^2) + |(log q - log q_nom) / prior_std|^2 sigma^2`` with SciPy's
``least_squares`` (trust-region reflective, bounded, the robust loss ``rho`` soft-l1), where
``sigma`` is the residuals' scale from a first fit without the prior: the prior pulls toward the
nominal model by as much as ``prior_std`` (a relative spread) says when data are few, and
vanishes as they grow. Positive parameters are fitted in log; residuals and their exact
Jacobian come from CasADi. The covariance is ``sigma^2 (J^T J)^-1`` at the solution. The data
are split: the last quarter of each episode is held out, the fit on the rest is judged by its
one-step error on the held-out transitions against the nominal model's, and the reported
estimate is the fit on all transitions.

SciPy's ``least_squares`` rather than a CasADi NLP: the problem is a small bounded nonlinear
least-squares problem, which it solves with robust losses built in and the Jacobian it needs
for the covariance at hand.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import casadi as ca
import numpy as np
from scipy.optimize import least_squares

from mpcmobo.mpc.codegen import compiled_library
from mpcmobo.systems.base import System

__all__ = [
    "Identification",
    "ModelFit",
    "Transitions",
    "at_bounds",
    "identification_bounds",
    "identify",
    "prediction_error",
]

HOLDOUT = 0.25  # the last quarter of each episode's transitions judges the fit
PRIOR_STD = 0.5  # the prior's spread of log q around the nominal value
AT_BOUND = 1e-3  # an estimate this close to a bound (relative; log for positive) sits on it


@dataclass
class Transitions:
    """Transitions ``(x_k, u_k) -> x_{k+1}`` of episodes: ``x`` (n, nx), ``u`` (n, nu),
    ``x_next`` (n, nx), ``episode`` (n,) the index of the episode each came from."""

    x: np.ndarray
    u: np.ndarray
    x_next: np.ndarray
    episode: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=int))

    @classmethod
    def empty(cls, nx: int, nu: int) -> Transitions:
        """No transition yet."""
        return cls(np.zeros((0, nx)), np.zeros((0, nu)), np.zeros((0, nx)), np.zeros(0, int))

    def add_episode(self, x: np.ndarray, u: np.ndarray) -> None:
        """The transitions of one episode: states ``x`` (T+1, nx), inputs ``u`` (T, nu); a
        transition with a non-finite value is left out."""
        x, u = np.asarray(x, float), np.asarray(u, float)
        T = min(len(u), len(x) - 1)
        xk, uk, xn = x[:T], u[:T], x[1 : T + 1]
        ok = np.all(np.isfinite(xk), 1) & np.all(np.isfinite(uk), 1) & np.all(np.isfinite(xn), 1)
        e = int(self.episode.max()) + 1 if len(self.episode) else 0
        self.x = np.vstack([self.x, xk[ok]])
        self.u = np.vstack([self.u, uk[ok]])
        self.x_next = np.vstack([self.x_next, xn[ok]])
        self.episode = np.concatenate([self.episode, np.full(int(ok.sum()), e)])

    def __len__(self) -> int:
        return len(self.x)

    def subset(self, mask: np.ndarray) -> Transitions:
        """The transitions where ``mask`` holds."""
        return Transitions(self.x[mask], self.u[mask], self.x_next[mask], self.episode[mask])

    def holdout_mask(self) -> np.ndarray:
        """True for the held-out transitions: the last quarter of each episode's (at least one
        when an episode has four or more)."""
        mask = np.zeros(len(self), dtype=bool)
        for e in np.unique(self.episode):
            rows = np.flatnonzero(self.episode == e)
            k = int(np.floor(HOLDOUT * len(rows)))
            if k:
                mask[rows[-k:]] = True
        return mask

    def state_dict(self) -> dict:
        """The arrays, as copies."""
        return {
            "x": self.x.copy(),
            "u": self.u.copy(),
            "x_next": self.x_next.copy(),
            "episode": self.episode.copy(),
        }

    @classmethod
    def from_state_dict(cls, d: dict) -> Transitions:
        """The inverse of :meth:`state_dict`."""
        return cls(
            np.array(d["x"], float),
            np.array(d["u"], float),
            np.array(d["x_next"], float),
            np.array(d["episode"], int),
        )


@dataclass(frozen=True)
class Identification:
    """The result of :func:`identify`.

    ``names`` the identified parameters, ``estimate`` their values and ``std`` their standard
    deviations (from ``cov``), ``params`` the whole model parameter vector with them in place;
    ``holdout_error`` and ``nominal_error`` the RMS scaled one-step error on the held-out
    transitions of the fit (on the others) and of the nominal model; ``n`` the transitions."""

    names: tuple[str, ...]
    estimate: np.ndarray
    std: np.ndarray
    cov: np.ndarray
    params: np.ndarray
    holdout_error: float
    nominal_error: float
    n: int
    success: bool
    message: str = ""

    @property
    def better(self) -> bool:
        """Whether the fit predicts the held-out transitions better than the nominal model."""
        return self.success and bool(self.holdout_error < self.nominal_error)


class _Residuals:
    """``q -> (r, dr/dq)`` of a system's transitions, from CasADi (one mapped function)."""

    def __init__(self, system: System, index: Sequence[int], nominal: np.ndarray) -> None:
        nx, nu = system.nx, system.nu
        x, u, xn = ca.SX.sym("x", nx), ca.SX.sym("u", nu), ca.SX.sym("xn", nx)
        q = ca.SX.sym("q", len(index))
        p = ca.SX(ca.DM(np.asarray(nominal, float)))
        for j, i in enumerate(index):
            p[i] = q[j]
        r = (system.discrete_step(x, u, p) - xn) / ca.DM(np.asarray(system.x_scale, float))
        self.fn = _compiled(ca.Function("residual", [x, u, xn, q], [r, ca.jacobian(r, q)]))
        self.nx, self.nq = nx, len(index)
        self._maps: dict[int, ca.Function] = {}
        self._last: tuple[bytes, int, tuple[np.ndarray, np.ndarray]] | None = None

    def __call__(self, data: Transitions, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = np.asarray(q, float).tobytes()
        if self._last is not None and self._last[:2] == (key, id(data)):
            return self._last[2]
        out = self._evaluate(data, q)
        self._last = (key, id(data), out)
        return out

    def _evaluate(self, data: Transitions, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        n = len(data)
        if n == 0:
            return np.zeros(0), np.zeros((0, self.nq))
        fm = self._maps.get(n)
        if fm is None:
            fm = self._maps[n] = self.fn.map(n)
        Q = np.repeat(np.asarray(q, float)[:, None], n, axis=1)
        r, J = fm(data.x.T, data.u.T, data.x_next.T, Q)
        r = np.asarray(r).T.reshape(-1)  # transition by transition
        if self.nq == 0:
            return r, np.zeros((len(r), 0))
        J = np.asarray(J).reshape(self.nx, n, self.nq).transpose(1, 0, 2).reshape(-1, self.nq)
        return r, J


def _compiled(fn: ca.Function) -> ca.Function:
    """``fn`` as compiled C (cached on disk, :mod:`mpcmobo.mpc.codegen`), about 50 times
    faster to evaluate on thousands of transitions; ``fn`` itself without a C compiler."""
    try:
        return ca.external(fn.name(), str(compiled_library([fn])))
    except RuntimeError:
        return fn


def prediction_error(system: System, data: Transitions, params: np.ndarray) -> float:
    """RMS of the scaled one-step prediction errors of the model with the whole parameter
    vector ``params`` on ``data`` (NaN without transitions)."""
    if len(data) == 0:
        return float("nan")
    r, _ = _Residuals(system, [], np.asarray(params, float))(data, np.zeros(0))
    return float(np.sqrt(np.mean(r**2)))


def _bounds(system: System, q0: np.ndarray) -> tuple[np.ndarray, ...]:
    """The identified parameters' bounds (those of the learnable model parameters: the
    nominal value times ``e^(+-model_log_range)``) and which are fitted in log."""
    m = system.mpc_spec.model_log_range
    pos = q0 > 0
    lo = np.where(pos, q0 * np.exp(-m), q0 - m * np.abs(q0) - 1)
    hi = np.where(pos, q0 * np.exp(m), q0 + m * np.abs(q0) + 1)
    return lo, hi, pos


def identification_bounds(
    system: System, names: Sequence[str] | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The bounds (lower, upper) of the identified parameters ``names`` (default: all of
    ``param_names``): the MPC's nominal value times ``e^(+-model_log_range)``."""
    pnames = list(system.param_names)
    index = [pnames.index(n) for n in (pnames if names is None else names)]
    lo, hi, _ = _bounds(system, np.asarray(system.models["imperfect"], float)[index])
    return lo, hi


def at_bounds(
    estimate: np.ndarray, lower: np.ndarray, upper: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Which entries of ``estimate`` sit on their lower and on their upper bound (within
    ``AT_BOUND``, relative: in log for positive bounds). A fit that ends on a bound was held by
    it: the plant's value may lie beyond (a wider ``model_log_range``), or the model's
    structure may be wrong."""
    q, lo, hi = (np.asarray(v, float) for v in (estimate, lower, upper))
    pos = lo > 0
    with np.errstate(divide="ignore", invalid="ignore"):
        d_lo = np.where(pos, np.log(q / lo), (q - lo) / np.maximum(np.abs(lo), 1.0))
        d_hi = np.where(pos, np.log(hi / q), (hi - q) / np.maximum(np.abs(hi), 1.0))
    return d_lo <= AT_BOUND, d_hi <= AT_BOUND


def _fit(
    res: _Residuals,
    data: Transitions,
    q0: np.ndarray,
    start: np.ndarray,
    prior_std: float,
    bounds: tuple[np.ndarray, ...],
) -> tuple[np.ndarray, np.ndarray, float, bool, str]:
    """The two-pass robust fit (module docstring): the estimate, ``J`` at it, ``sigma``,
    success and SciPy's message."""
    system_lo, system_hi, pos = bounds

    def to_q(v: np.ndarray) -> np.ndarray:
        return np.where(pos, np.exp(v), v)

    def from_q(q: np.ndarray) -> np.ndarray:
        return np.where(pos, np.log(np.maximum(q, 1e-300)), q)

    v_lo, v_hi, v_nom = from_q(system_lo), from_q(system_hi), from_q(q0)
    v = np.clip(from_q(start), v_lo + 1e-12, v_hi - 1e-12)

    def run(prior_w: float, v_start: np.ndarray) -> Any:
        def fun(vv: np.ndarray) -> np.ndarray:
            r, _ = res(data, to_q(vv))
            return np.concatenate([r, prior_w * (vv - v_nom) / prior_std])

        def jac(vv: np.ndarray) -> np.ndarray:
            _, J = res(data, to_q(vv))
            J = J * np.where(pos, to_q(vv), 1.0)[None, :]  # dq/dv = q in log coordinates
            return np.vstack([J, prior_w * np.eye(len(vv)) / prior_std])

        # a trial step far out (a model that runs away over one step) overflows the robust
        # loss: its cost is inf and the step is refused, which is all the warning would say
        with np.errstate(over="ignore"):
            return least_squares(
                fun,
                v_start,
                jac=jac,
                bounds=(v_lo, v_hi),
                loss="soft_l1",
                f_scale=max(prior_w, 1e-9),
                x_scale="jac",
                max_nfev=200,
            )

    first = run(0.0, v)
    r1, _ = res(data, to_q(first.x))
    sigma = float(1.4826 * np.median(np.abs(r1))) if len(r1) else 0.0  # robust scale
    out = run(sigma, first.x)
    q = to_q(out.x)
    _, J = res(data, q)  # dr/dq at the estimate, for the covariance
    return q, J, sigma, bool(out.success), str(out.message)


class ModelFit:
    """The identification of the parameters ``names`` (default: all) of ``system``'s model,
    the others at ``nominal`` (default: the MPC's model, ``"imperfect"``), built once and fitted
    again as data come in (:meth:`fit`). Where the parameters sit in theta (the
    ``model_<name>`` entries of the system's parameterization, when it has them) makes the seam
    through which a learner puts an identified model into its MPC (:meth:`theta_with`)."""

    def __init__(
        self,
        system: System,
        names: Sequence[str] | None = None,
        nominal: np.ndarray | None = None,
        *,
        prior_std: float = PRIOR_STD,
    ) -> None:
        pnames = list(system.param_names)
        self.names = tuple(pnames if names is None else names)
        unknown = [n for n in self.names if n not in pnames]
        if unknown:
            raise ValueError(f"unknown model parameter(s) {unknown}; the system has {pnames}")
        if not self.names:
            raise ValueError(f"the system '{system.name}' declares no model parameter to identify")
        self.system = system
        self.index = [pnames.index(n) for n in self.names]
        self.nominal = np.asarray(
            system.models["imperfect"] if nominal is None else nominal, float
        ).copy()
        self.prior_std = float(prior_std)
        theta_names = list(system.parameterization.names)
        self.theta_index = [
            theta_names.index(f"model_{n}") if f"model_{n}" in theta_names else -1
            for n in self.names
        ]
        self._res = _Residuals(system, self.index, self.nominal)
        self.bounds = _bounds(system, self.nominal[self.index])

    def error(self, data: Transitions, params: np.ndarray) -> float:
        """RMS scaled one-step prediction error of the model with ``params`` (the identified
        entries; the others nominal) on ``data`` (NaN without transitions)."""
        if len(data) == 0:
            return float("nan")
        r, _ = self._res(data, np.asarray(params, float))
        return float(np.sqrt(np.mean(r**2)))

    def fit(self, data: Transitions, start: np.ndarray | None = None) -> Identification:
        """Fit on ``data`` (module docstring); ``start``: the previous estimate (default:
        nominal), to warm-start."""
        q0 = self.nominal[self.index]
        hold = data.holdout_mask()
        train = data.subset(~hold) if hold.any() and (~hold).sum() >= len(q0) else data
        held = data.subset(hold) if hold.any() else data
        x0 = q0 if start is None else np.asarray(start, float)
        if len(train) == 0:
            inf = np.full(len(q0), np.inf)
            return Identification(
                self.names,
                q0,
                inf,
                np.diag(inf),
                self.nominal.copy(),
                np.nan,
                np.nan,
                0,
                False,
                "no transitions",
            )
        q_train, _, _, ok_train, _ = _fit(self._res, train, q0, x0, self.prior_std, self.bounds)
        q, J, _, ok, message = _fit(self._res, data, q0, q_train, self.prior_std, self.bounds)
        params = self.nominal.copy()
        params[self.index] = q
        r, _ = self._res(data, q)
        s2 = float(r @ r) / max(1, len(r) - len(q))
        cov = s2 * np.linalg.pinv(J.T @ J)
        return Identification(
            names=self.names,
            estimate=q,
            std=np.sqrt(np.maximum(np.diag(cov), 0.0)),
            cov=cov,
            params=params,
            holdout_error=self.error(held, q_train),
            nominal_error=self.error(held, q0),
            n=len(data),
            success=ok and ok_train and bool(np.all(np.isfinite(q))),
            message=message,
        )

    def theta_with(self, theta: np.ndarray, estimate: np.ndarray) -> np.ndarray:
        """``theta`` with its model entries set to the identified ``estimate``."""
        if any(i < 0 for i in self.theta_index):
            raise ValueError(
                "the MPC's theta has no entries for the identified parameters: build the "
                "system with MPCSpec.identify (the study's [system] identify)"
            )
        out = np.array(theta, float)
        out[self.theta_index] = np.asarray(estimate, float)
        return out

    def estimate_of(self, theta: np.ndarray) -> np.ndarray:
        """The identified parameters' values in ``theta``."""
        return np.asarray(theta, float)[self.theta_index].copy()


def identify(
    system: System,
    data: Transitions,
    nominal: np.ndarray | None = None,
    names: Sequence[str] | None = None,
    *,
    start: np.ndarray | None = None,
    prior_std: float = PRIOR_STD,
) -> Identification:
    """Fit the model parameters ``names`` (default: all of ``system.param_names``) to the
    transitions ``data``, the others at ``nominal`` (default: the MPC's model); see
    :class:`ModelFit`."""
    return ModelFit(system, names, nominal, prior_std=prior_std).fit(data, start)
