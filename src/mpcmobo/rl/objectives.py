r"""The four per-episode objectives of MPC-CDPG-MOBO (paper, section 4), all to be minimised.

* f1, closed-loop performance (eq. cl_perf): :math:`\tilde J = \frac1T\sum_{k=0}^{T-1}\gamma^k L_k`
* f2, optimality condition (eq. f2 with eq. DPG):
  :math:`\frac1T\sum_k \|\nabla_\theta\pi_k\nabla_\theta\pi_k^\top w\|`
* f3, critic drift (eq. f3): :math:`\max(0, V^c_\ell - V^c_{\ell-1})`,
  :math:`V^c = \sum_k V^\nu(x_k)` (eq. nu)
* f4, Lyapunov decrease (eq. f4): :math:`\beta\sum_k \max(0, V_\theta(x_{k+1}) - V_\theta(x_k))`

Index conventions (the paper's are loose: it sums k = 0..T_f in eq. cl_perf but divides by T_f,
and k = 1..T_f elsewhere): an episode has T applied inputs u_0..u_{T-1} and T+1 states x_0..x_T;
f1 averages the T stage costs, f2 the steps with a policy sensitivity, f4 sums the T transitions.
"""

from __future__ import annotations

import numpy as np

from mpcmobo.mpc.records import EpisodeRecord
from mpcmobo.rl.critic import CriticResult


def f1_closed_loop_cost(record: EpisodeRecord, gamma: float | None = None) -> float:
    r"""f1 = J~(theta) = (1/T) sum_{k=0}^{T-1} gamma^k L(x_k, u_k)  (eq. cl_perf).

    ``gamma`` defaults to ``record.gamma``. L is the plant's stage cost of the applied input
    (policy plus exploration). NaN if any stage cost is non-finite (a diverged episode), so that
    the outcome is dropped rather than fed to a surrogate as a number.
    """
    g = float(record.gamma) if gamma is None else float(gamma)
    L = np.asarray(record.L, dtype=float).reshape(-1)
    T = L.shape[0]
    if T == 0 or not np.all(np.isfinite(L)):
        return float("nan")
    return float(np.sum(g ** np.arange(T) * L) / T)  # eq. cl_perf


def mean_stage_cost(record: EpisodeRecord) -> float:
    """Plain (undiscounted) mean of the stage costs L_k, as used by the evaluation protocol."""
    L = np.asarray(record.L, dtype=float).reshape(-1)
    if L.shape[0] == 0 or not np.all(np.isfinite(L)):
        return float("nan")
    return float(np.mean(L))


def f2_optimality(critic_result: CriticResult) -> float:
    r"""f2 = (1/T) sum_k ||grad pi_k grad pi_k^T w||  (eq. f2, eq. DPG).

    The mean is over the steps whose policy sensitivity is available (``policy_mask``; all steps
    if the result has no mask). Zero when the critic failed (``w = 0``); check
    ``critic_result.ok`` to tell a failed fit from a stationary point.
    """
    norms = np.asarray(critic_result.grad_norms, dtype=float).reshape(-1)
    m = np.asarray(critic_result.policy_mask, dtype=bool).reshape(-1)
    if m.shape != norms.shape:
        m = np.isfinite(norms)
    m = m & np.isfinite(norms)
    return float(np.mean(norms[m])) if np.any(m) else 0.0  # eq. f2


def f3_critic_drift(Vc: float, previous_Vc: float | None) -> float:
    r"""f3 = max(0, V^c_l - V^c_{l-1})  (eq. f3), V^c = sum_k V^nu(x_k) (eq. nu).

    0 for the first episode (``previous_Vc is None``) and whenever either value is non-finite
    (a failed critic does not produce drift).
    """
    if previous_Vc is None:
        return 0.0
    Vc, prev = float(Vc), float(previous_Vc)
    if not (np.isfinite(Vc) and np.isfinite(prev)):
        return 0.0
    return max(0.0, Vc - prev)  # eq. f3


def f4_lyapunov(record: EpisodeRecord, beta: float = 1.0) -> float:
    r"""f4 = beta sum_{k=0}^{T-1} max(0, V_theta(x_{k+1}) - V_theta(x_k))  (eq. f4), beta > 0.

    Only increases of the MPC value count; pairs where either solve failed or either value is
    non-finite are skipped.
    """
    V = np.asarray(record.V, dtype=float).reshape(-1)
    ok = np.isfinite(V) & np.asarray(record.success, dtype=bool).reshape(-1)
    pair = ok[:-1] & ok[1:]
    if not np.any(pair):
        return 0.0
    inc = np.maximum(0.0, V[1:][pair] - V[:-1][pair])
    return float(beta * np.sum(inc))  # eq. f4


def objectives(
    record: EpisodeRecord,
    critic_result: CriticResult,
    previous_Vc: float | None,
    beta: float = 1.0,
) -> np.ndarray:
    """[f1, f2, f3, f4] of one episode (eq. cl_perf, f2, f3, f4), all to be minimised.

    ``previous_Vc`` is ``Vc`` of the previous episode's critic (``None`` for the first episode);
    the caller keeps it, e.g. ``previous_Vc = result.Vc if np.isfinite(result.Vc) else previous``.
    """
    drift = f3_critic_drift(critic_result.Vc, previous_Vc)
    return np.array(
        [
            f1_closed_loop_cost(record),
            f2_optimality(critic_result),
            drift,
            f4_lyapunov(record, beta),
        ],
        dtype=float,
    )
