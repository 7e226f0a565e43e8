r"""Compatible critic of the MPC-based deterministic policy gradient (paper, sections 2.2 and 4).

From one closed-loop episode (an :class:`~mpcmobo.mpc.records.EpisodeRecord`) the critic fits

* the value baseline (eq. nu)

  .. math:: V^\nu(x) = V_\theta(x) + \nabla_\theta V_\theta(x)^\top \nu,

  i.e. features :math:`\phi_k = \nabla_\theta V_\theta(x_k)` on top of the MPC value, by LSTDV
  (eq. lstdv_update, or the LSTD(0) fixed point: ``method``);
* the compatible advantage (eq. Q_w, eq. adv)

  .. math:: A^w(x_k, u_k) = \Psi_k^\top w, \qquad
            \Psi_k = \nabla_\theta \pi_\theta(x_k)\,(u_k - \pi_\theta(x_k)),

  by LSTDQ (eq. lstdq_update, target: ``q_target``), and from it
* the deterministic policy gradient (eq. DPG)

  .. math:: \nabla_\theta J \approx \frac{1}{T} \sum_k
            \nabla_\theta\pi_\theta(x_k)\nabla_\theta\pi_\theta(x_k)^\top w .

The policy *minimises* the cost, so ``grad`` is the gradient of the closed-loop cost J, which
the actor descends. The fits are scaled ridge least squares (:func:`ridge_lstsq`,
:func:`lstd_solve`) on the usable transitions (:func:`transition_mask`); a failed fit gives
zeros and ``ok=False``, never NaN. :class:`CompatibleCritic` documents the options.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import scipy.linalg

from mpcmobo.mpc.records import EpisodeRecord

_METHODS = ("lstd", "paper")
_Q_TARGETS = ("V_theta", "V_nu")


@dataclass
class CriticResult:
    """Output of :meth:`CompatibleCritic.fit` for one episode.

    Arrays are indexed by step k = 0..T-1 (``V_nu``: states 0..T). ``grad`` is the gradient of the
    closed-loop cost (descend it). ``mask`` marks the transitions used by the LSTD fits and
    ``policy_mask`` the steps whose policy sensitivity is available (those enter ``grad`` and
    ``grad_norms``; elsewhere ``advantage`` and ``grad_norms`` are 0).
    """

    nu: np.ndarray  # (n_theta,) value-baseline weights (eq. nu)
    w: np.ndarray  # (n_theta,) compatible advantage weights (eq. adv)
    advantage: np.ndarray  # (T,) A^w_k = Psi_k^T w
    grad: np.ndarray  # (n_theta,) policy gradient of J (eq. DPG), mean over policy_mask
    grad_norms: np.ndarray  # (T,) ||grad pi_k grad pi_k^T w||
    V_nu: np.ndarray  # (T+1,) V^nu(x_k) (NaN where V_theta is unavailable)
    Vc: float  # sum_k V^nu(x_k) over the T+1 states (NaN if no state is available)
    valid_steps: int  # number of transitions used by the fits
    ok: bool  # both fits succeeded
    nu_ok: bool = True
    w_ok: bool = True
    mask: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))  # (T,)
    policy_mask: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=bool))  # (T,)
    method: str = "lstd"
    q_target: str = "V_nu"

    @property
    def mean_abs_advantage(self) -> float:
        """Mean |A^w_k| over the transitions used by the fit (0 if none)."""
        if not np.any(self.mask):
            return 0.0
        return float(np.mean(np.abs(self.advantage[self.mask])))


def _finite_rows(a: np.ndarray) -> np.ndarray:
    """True for each leading-index entry whose trailing entries are all finite."""
    a = np.asarray(a, dtype=float)
    if a.ndim == 1:
        return np.isfinite(a)
    return np.all(np.isfinite(a.reshape(a.shape[0], -1)), axis=1)


def transition_mask(record: EpisodeRecord) -> np.ndarray:
    """(T,) bool: transition k usable by the critic.

    Requires ``success[k]`` and ``success[k+1]`` and finite ``L_k``, ``u_k``, ``pi_k``,
    ``grad pi_k``, ``V(x_k)``, ``V(x_{k+1})``, ``grad V(x_k)``, ``grad V(x_{k+1})``.
    """
    T = record.steps
    success = np.asarray(record.success, dtype=bool).reshape(-1)
    if success.shape[0] != T + 1:
        raise ValueError(f"record.success has {success.shape[0]} entries, expected {T + 1}")
    V_ok = np.isfinite(np.asarray(record.V, dtype=float))
    dV_ok = _finite_rows(record.dV)
    state_ok = success & V_ok & dV_ok
    return (
        state_ok[:-1]
        & state_ok[1:]
        & np.isfinite(np.asarray(record.L, dtype=float))
        & _finite_rows(record.u)
        & _finite_rows(record.pi)
        & _finite_rows(record.dpi)
    )


def _column_scale(F: np.ndarray) -> np.ndarray:
    """Per-column root-mean-square of ``F`` (1 where a column is all zero)."""
    s = np.sqrt(np.mean(F * F, axis=0)) if F.shape[0] else np.ones(F.shape[1])
    return np.where((s > 0) & np.isfinite(s), s, 1.0)


def ridge_lstsq(F: np.ndarray, y: np.ndarray, ridge: float) -> np.ndarray | None:
    r"""Scaled ridge least squares: argmin_p ||F p - y||^2 + rho n ||D p||^2.

    Columns of ``F`` (n x m) are scaled to unit RMS (D = diag of the scales), the system
    :math:`[F D^{-1}; \sqrt{\rho n} I] z = [y; 0]` is solved by ``lstsq`` and ``p = D^{-1} z`` is
    returned; ``None`` if degenerate (no rows, all-zero features) or non-finite.
    """
    n = F.shape[0]
    if n == 0 or not np.any(F):
        return None
    s = _column_scale(F)
    return _ridge_gelsd(F / s, y, np.sqrt(ridge * n), s)


def lstd_solve(
    Phi: np.ndarray, Phi_next: np.ndarray, delta: np.ndarray, gamma: float, ridge: float
) -> np.ndarray | None:
    r"""LSTD(0) fixed point for V^nu = V_theta + phi^T nu (method "lstd").

    Solves :math:`\sum_k \phi_k(\phi_k - \gamma\phi_{k+1})^\top \nu = \sum_k \phi_k\delta_k`
    after per-column scaling :math:`\phi = D\phi_s` (``A_s = D^{-1} A D^{-1}``, ``b_s = D^{-1} b``,
    ``nu = D^{-1} z``), by ``lstsq`` on :math:`[A_s; \sqrt{\rho} n I] z = [b_s; 0]`.
    Returns ``None`` if degenerate or non-finite.
    """
    n = Phi.shape[0]
    if n == 0 or not np.any(Phi):
        return None
    s = _column_scale(np.vstack([Phi, Phi_next]))
    Ps, Pns = Phi / s, Phi_next / s
    A = Ps.T @ (Ps - gamma * Pns)
    b = Ps.T @ delta
    return _ridge_gelsd(A, b, np.sqrt(ridge) * n, s)


def _ridge_gelsd(A: np.ndarray, b: np.ndarray, weight: float, s: np.ndarray) -> np.ndarray | None:
    """``z / s`` for ``z`` the least-squares solution (LAPACK gelsd) of ``[A; w I] z = [b; 0]``
    (no ridge rows when ``w = 0``): the shared last step of :func:`ridge_lstsq` and
    :func:`lstd_solve`, whose columns were scaled by ``s``. ``None`` if it fails or is not
    finite."""
    m = A.shape[1]
    if weight > 0:
        A = np.vstack([A, weight * np.eye(m)])
        b = np.concatenate([b, np.zeros(m)])
    try:
        z = scipy.linalg.lstsq(A, b, lapack_driver="gelsd")[0]
    except (np.linalg.LinAlgError, ValueError):
        return None
    p = z / s
    return p if np.all(np.isfinite(p)) else None


class CompatibleCritic:
    r"""LSTDV / LSTDQ compatible critic and DPG gradient of one episode (see the module docstring).

    Parameters
    ----------
    gamma:
        Discount factor; ``None`` takes ``record.gamma``.
    ridge:
        Relative ridge regularisation :math:`\rho`. Features are scaled per column to unit
        root-mean-square (the CSTR's sensitivities span many orders of magnitude) and the
        scaling is undone in the result, so :math:`\rho` is relative to the per-sample second
        moment of the features and dimensionless; ``ridge=0`` gives the minimum-norm
        least-squares solution. The regressions are solved with ``scipy.linalg.lstsq`` on the
        stacked, ridge-augmented feature matrix :math:`[\Phi_s; \sqrt{\rho n} I]` (never by
        forming normal equations); the LSTD system :math:`A_s z = b_s` (n_theta x n_theta) by
        ``lstsq`` on :math:`[A_s; \sqrt{\rho} n I]`.
    method:
        The LSTDV rule. ``"paper"`` is eq. lstdv_update as printed,

        .. math:: \nu = \Xi_\nu^{-1} b_\nu,\quad \Xi_\nu = \sum_k \phi_k\phi_k^\top,\quad
                  b_\nu = \sum_k \phi_k\,\big(L_k + \gamma V_\theta(x_{k+1}) - V_\theta(x_k)\big),

        the least-squares regression of the one-step TD error *of* :math:`V_\theta` on the
        features: :math:`V^\nu(x_k) \approx L_k + \gamma V_\theta(x_{k+1})`. It bootstraps on
        the MPC value :math:`V_\theta` rather than on :math:`V^\nu` itself, so it is one fitted
        value-iteration step from :math:`V_\theta`, not a fixed point of the Bellman equation;
        when :math:`V_\theta` is far from the true value of the policy (the usual case with an
        imperfect model) the result is biased.

        ``"lstd"`` (the default) is the LSTD(0) fixed point of the projected Bellman equation
        for :math:`V^\nu`, i.e. :math:`\sum_k \phi_k (L_k + \gamma V^\nu(x_{k+1}) -
        V^\nu(x_k)) = 0`:

        .. math:: A\nu = b,\quad A = \sum_k \phi_k(\phi_k - \gamma\phi_{k+1})^\top,\quad
                  b = \sum_k \phi_k\,\delta_k,\quad
                  \delta_k = L_k + \gamma V_\theta(x_{k+1}) - V_\theta(x_k).

        If the Bellman equation holds exactly for some :math:`V^\nu`, the LSTD rule recovers
        that :math:`\nu` while the paper's rule in general does not (it does only if
        :math:`\gamma = 0` or :math:`\nabla V_\theta(x_{k+1})^\top\nu = 0`); see the tests.
        This is why it is the default.
    q_target:
        The value of x_{k+1} in the LSTDQ target (eq. lstdq_update)
        :math:`\delta^V_k = L_k + \gamma V(x_{k+1}) - V^\nu(x_k)`: ``"V_theta"``,
        :math:`V_\theta(x_{k+1})` as printed in the paper, or ``"V_nu"``,
        :math:`V^\nu(x_{k+1})`, which is what the paper's own derivation (substituting
        :math:`Q^w = A^w + V^\nu` into eq. LSTDQ_eq) gives. The difference
        :math:`-\gamma\nabla V_\theta(x_{k+1})^\top\nu` depends on the explored input through
        :math:`x_{k+1}` and therefore correlates with :math:`\Psi_k`, biasing :math:`w`.
        ``None`` (the default) follows the method: ``"V_theta"`` for ``method="paper"``,
        ``"V_nu"`` for ``"lstd"``.
    min_valid_steps:
        Fewer usable transitions than this makes the fit fail (``ok=False``).
    weighting:
        How the DPG averages the steps: ``"uniform"`` (the paper's mean over the steps) or
        ``"discounted"`` (weights gamma^k: the gradient of the discounted closed-loop cost from
        the episode's start).
    """

    def __init__(
        self,
        gamma: float | None,
        ridge: float = 1e-6,
        method: str = "lstd",
        q_target: str | None = None,
        min_valid_steps: int = 2,
        weighting: str = "uniform",
    ) -> None:
        if weighting not in ("uniform", "discounted"):
            raise ValueError(f"weighting must be 'uniform' or 'discounted', got {weighting!r}")
        self.weighting = weighting
        if method not in _METHODS:
            raise ValueError(f"method must be one of {_METHODS}, got {method!r}")
        if q_target is None:
            q_target = "V_theta" if method == "paper" else "V_nu"
        if q_target not in _Q_TARGETS:
            raise ValueError(f"q_target must be one of {_Q_TARGETS}, got {q_target!r}")
        if ridge < 0 or not np.isfinite(ridge):
            raise ValueError("ridge must be finite and >= 0")
        self.gamma = None if gamma is None else float(gamma)
        self.ridge = float(ridge)
        self.method = method
        self.q_target = q_target
        self.min_valid_steps = max(1, int(min_valid_steps))

    def fit(self, record: EpisodeRecord) -> CriticResult:
        """Fit nu (eq. lstdv_update), w (eq. lstdq_update) and the DPG gradient (eq. DPG).

        Transition k (from x_k to x_{k+1}) is used only if both solves succeeded and every
        quantity it touches is finite (:func:`transition_mask`). If fewer than
        ``min_valid_steps`` transitions remain, or a system is degenerate (all features zero,
        non-finite solution), the corresponding part returns zeros and ``ok`` is False: ``w``,
        ``grad`` and ``advantage`` are then zeros, never NaN.
        """
        gamma = float(record.gamma) if self.gamma is None else self.gamma
        ep = _Episode.from_record(record)
        mask = transition_mask(record)
        idx = np.flatnonzero(mask)
        enough = idx.size >= self.min_valid_steps
        nu = self._lstdv(ep, idx, gamma) if enough else None
        nu_ok = nu is not None
        if nu is None:
            nu = np.zeros(ep.n_theta)
        V_nu, Vc = _value_baseline(ep, nu)
        Psi, policy_mask = _compatible_features(ep)
        w = self._lstdq(ep, idx, gamma, V_nu, Psi) if enough and nu_ok else None
        w_ok = w is not None
        ok = nu_ok and w_ok
        if not ok:
            w = np.zeros(ep.n_theta)
        # A^w_k = Psi_k^T w  (eq. adv, eq. Q_w)
        advantage = Psi @ w
        grad, grad_norms = self._policy_gradient(ep, policy_mask, w, gamma)  # type: ignore[arg-type]  # zeros if not ok
        if not (np.all(np.isfinite(grad)) and np.all(np.isfinite(advantage))):
            # overflow in the products: treat as a failed fit rather than leak inf / NaN
            ok, w_ok = False, False
            w, advantage, grad = np.zeros(ep.n_theta), np.zeros(ep.T), np.zeros(ep.n_theta)
            grad_norms = np.zeros(ep.T)
        return CriticResult(
            nu=nu,
            w=w,  # type: ignore[arg-type]  # zeros if not ok
            advantage=advantage,
            grad=grad,
            grad_norms=grad_norms,
            V_nu=V_nu,
            Vc=Vc,
            valid_steps=int(idx.size),
            ok=bool(ok),
            nu_ok=bool(nu_ok),
            w_ok=bool(w_ok),
            mask=mask,
            policy_mask=policy_mask,
            method=self.method,
            q_target=self.q_target,
        )

    def _lstdv(self, ep: _Episode, idx: np.ndarray, gamma: float) -> np.ndarray | None:
        """nu of V^nu = V_theta + dV^T nu (eq. nu) by LSTDV (eq. lstdv_update) or LSTD(0)."""
        Phi, Phi_next = ep.dV[idx], ep.dV[idx + 1]
        delta = ep.L[idx] + gamma * ep.V[idx + 1] - ep.V[idx]  # TD error of V_theta
        if self.method == "paper":
            return ridge_lstsq(Phi, delta, self.ridge)  # Xi_nu nu = b_nu, as least squares
        return lstd_solve(Phi, Phi_next, delta, gamma, self.ridge)

    def _lstdq(
        self, ep: _Episode, idx: np.ndarray, gamma: float, V_nu: np.ndarray, Psi: np.ndarray
    ) -> np.ndarray | None:
        """w of A^w = Psi^T w by LSTDQ (eq. lstdq_update) on the target delta^V_k."""
        V_next = V_nu[idx + 1] if self.q_target == "V_nu" else ep.V[idx + 1]
        delta_V = ep.L[idx] + gamma * V_next - V_nu[idx]  # delta^V_k
        if not np.all(np.isfinite(delta_V)):
            return None
        return ridge_lstsq(Psi[idx], delta_V, self.ridge)

    def _policy_gradient(
        self, ep: _Episode, policy_mask: np.ndarray, w: np.ndarray, gamma: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """grad_theta J (eq. DPG) and the per-step norms ||grad pi_k grad pi_k^T w||.

        grad_theta J_k = grad pi_k grad pi_k^T w; the mean over the steps with a sensitivity
        ((1/T) sum_k), which the actor descends (eq. theta). ``weighting="discounted"``:
        sum_k gamma^k g_k / sum_k gamma^k, the deterministic policy gradient theorem's
        discounted state distribution, i.e. the gradient of the discounted closed-loop cost f1
        from the episode's start (the paper's rule is the uniform mean).
        """
        T, n_theta, dpi = ep.T, ep.n_theta, ep.dpi
        g_k = np.zeros((T, n_theta))
        g_k[policy_mask] = np.einsum(
            "kpa,kqa,q->kp", dpi[policy_mask], dpi[policy_mask], w, optimize=True
        )
        if not np.any(policy_mask):
            grad = np.zeros(n_theta)
        elif self.weighting == "discounted":
            wk = gamma ** np.arange(T, dtype=float) * policy_mask
            grad = (wk @ g_k) / wk.sum()
        else:
            grad = g_k[policy_mask].mean(axis=0)
        return grad, np.linalg.norm(g_k, axis=1)


@dataclass
class _Episode:
    """The arrays of an :class:`EpisodeRecord` the critic uses, as float arrays of fixed shape."""

    T: int
    n_theta: int
    dpi: np.ndarray  # (T, n_theta, nu)
    V: np.ndarray  # (T+1,)
    dV: np.ndarray  # (T+1, n_theta)
    L: np.ndarray  # (T,)
    du: np.ndarray  # (T, nu) exploration u_k - pi_k
    success: np.ndarray  # (T+1,) bool

    @classmethod
    def from_record(cls, record: EpisodeRecord) -> _Episode:
        T = record.steps
        dpi = np.asarray(record.dpi, dtype=float).reshape(T, -1, np.asarray(record.u).shape[1])
        n_theta = dpi.shape[1]
        return cls(
            T=T,
            n_theta=n_theta,
            dpi=dpi,
            V=np.asarray(record.V, dtype=float).reshape(T + 1),
            dV=np.asarray(record.dV, dtype=float).reshape(T + 1, n_theta),
            L=np.asarray(record.L, dtype=float).reshape(T),
            du=np.asarray(record.u, dtype=float) - np.asarray(record.pi, dtype=float),
            success=np.asarray(record.success, dtype=bool).reshape(-1),  # checked by the mask
        )


def _value_baseline(ep: _Episode, nu: np.ndarray) -> tuple[np.ndarray, float]:
    """V^nu(x_k) = V_theta(x_k) + grad V_theta(x_k)^T nu (eq. nu) and Vc = sum_k V^nu(x_k).

    NaN where V_theta is unavailable; with missing states Vc is (T+1) x their mean, so that
    failed solves do not shrink the sum (and so fake a decrease in f3).
    """
    state_ok = np.isfinite(ep.V) & _finite_rows(ep.dV)
    V_nu = np.full(ep.T + 1, np.nan)
    V_nu[state_ok] = ep.V[state_ok] + ep.dV[state_ok] @ nu
    n_states = int(np.count_nonzero(state_ok))
    Vc = float(np.sum(V_nu[state_ok]) * (ep.T + 1) / n_states) if n_states else float("nan")
    return V_nu, Vc


def _compatible_features(ep: _Episode) -> tuple[np.ndarray, np.ndarray]:
    """Psi_k = grad pi_k (u_k - pi_k) (eq. Q_w) and the steps whose policy sensitivity exists."""
    policy_mask = ep.success[:-1] & _finite_rows(ep.dpi) & _finite_rows(ep.du)
    Psi = np.zeros((ep.T, ep.n_theta))
    Psi[policy_mask] = np.einsum("kpa,ka->kp", ep.dpi[policy_mask], ep.du[policy_mask])
    return Psi, policy_mask
