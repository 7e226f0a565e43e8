"""The interior-point continuation of warm solves: the path between the Newton steps and IPOPT.

The Newton steps of :mod:`mpcmobo.mpc.solve` need a strictly interior start close to the root.
When the new state violates a relaxed row of the shifted plan (a state bound that its slack no
longer covers), or the steps do not converge, :func:`continuation` solves the same barrier
problem on the same Newton system, as an interior-point method warm-started from the shifted
plan would (:func:`recentre`, then :func:`continuation`):

1. re-centre: every slack with a row at ``H > -gap tau`` (not strictly interior) is raised until
   its tightest row is at ``-m0 / S`` (``S``: the sum of the multipliers of the slack's rows,
   which that row keeps, less the central-path multipliers ``m0 / (-H)`` of the slack's other
   rows; a row is linear in its slack, so this is exact, and the slack's stationarity holds);
2. follow the central path: Newton steps on ``R_m(y, p) = 0`` (the KKT residual at the barrier
   parameter ``m``, :attr:`~mpcmobo.mpc.kkt.KKTSystem.newton_mu`) with fraction-to-boundary
   steps, from ``m = m0``; once ``|R_m|_inf <= kappa m``, ``m`` falls superlinearly,
   ``m <- max(tau, min(m / 5, m^1.5))``;
3. polish at ``m = tau`` with the Newton steps of the barrier problem itself until
   ``|R|_inf <= tol`` at a strictly interior point: the root the Newton path and IPOPT stop at,
   so the policy and its sensitivities are the ones of eq. nabla_pi.

Where the path from the re-centred shifted plan fails or ends at a saddle point, the previous
solution's multipliers are what misled it: the continuation restarts from the shifted plan
itself put on the central path at ``m = 1e-2`` (``RESTART_BARRIER``: every multiplier 1,
re-centred, then every ``mu`` at ``m / -H``, as :func:`cold_start` does with the cold guess).

Without a warm start (the first step of an episode), :func:`cold_start` puts the cold guess on
the central path at a larger barrier parameter (``COLD_BARRIERS``: 1, then 0.1): every
multiplier 1, re-centred, then every ``mu`` at ``m / -H``, and the same continuation follows
from there (the embedded controller's cold path, :mod:`mpcmobo.mpc.embedded`, step for step;
without IPOPT, the embedded controller takes it also where the path from its warm start fails).

A root is a minimum or a saddle point of the barrier problem: the paths have no merit function.
The solver accepts a root of theirs only at a minimum
(:meth:`~mpcmobo.mpc.kkt.KKTSystem.is_minimum`); a saddle point, dearer, goes to IPOPT.

Every step is one call of a (generated) CasADi function, at most ``max_steps`` of them per path.
There is no line search: a step that leaves the interior, or running out of steps, ends the
path (None), and IPOPT solves.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from mpcmobo.mpc.kkt import KKTSystem


@dataclass(frozen=True)
class Continuation:
    """The settings of :func:`recentre` and :func:`continuation` (module docstring): at most
    ``max_steps`` Newton steps; the rows at ``H > -gap tau`` re-centred, to
    ``H = -m0 / max(S, m0 / delta)`` (at most ``delta`` inside); the first barrier parameter
    ``m0``; the path's tolerance ``kappa m``."""

    max_steps: int = 30
    delta: float = 1e-2
    gap: float = 1e-3
    m0: float = 1e-3
    kappa: float = 10.0


#: the barrier parameters at which the continuation from the cold guess starts, in turn
COLD_BARRIERS = (1.0, 0.1)
#: the barrier parameter at which the continuation restarts from the shifted plan on the
#: central path (:func:`cold_continuation` from the shifted plan)
RESTART_BARRIER = 1e-2


def recentre(
    kkt: KKTSystem,
    w: np.ndarray,
    lam: np.ndarray,
    mu: np.ndarray,
    p: np.ndarray,
    settings: Continuation,
) -> np.ndarray | None:
    """The start ``y = (w, lambda, mu)`` of the path from the shifted plan ``w`` and its
    multipliers (step 1 of the module docstring), or None when a row that no slack relaxes is
    not strictly interior."""
    H = kkt.rows_call(w, p)[0].reshape(-1)
    slack, m0 = kkt.slack_of_row, settings.m0
    bad = H > -settings.gap * kkt.tau
    if np.any(slack[bad] < 0) or not np.all(np.isfinite(H)):
        return None
    raised = np.unique(slack[bad])
    w, mu = w.copy(), mu.copy()
    for k in raised:
        rows = np.flatnonzero(slack == k)
        w[k] += np.max(H[rows]) + m0 / max(float(np.sum(mu[rows])), m0 / settings.delta)
    H = kkt.rows_call(w, p)[0].reshape(-1)
    for k in raised:
        rows = np.flatnonzero(slack == k)
        tight = rows[np.argmax(H[rows])]
        others = rows[rows != tight]
        total = float(np.sum(mu[rows]))
        mu[others] = m0 / np.maximum(-H[others], 1e-300)
        mu[tight] = max(total - float(np.sum(mu[others])), m0 / max(-H[tight], 1e-300))
    return np.concatenate([w, lam, np.maximum(mu, 1e-300)])


def continuation(
    kkt: KKTSystem,
    y: np.ndarray,
    p: np.ndarray,
    tol: float,
    settings: Continuation,
) -> tuple[np.ndarray, float, int] | None:
    """From a re-centred start ``y``, (the root y of ``R(., p)`` with ``|R|_inf <= tol``, the
    scaled cost there, the steps taken), or None (steps 2 and 3 of the module docstring)."""
    tau, m = kkt.tau, max(settings.m0, kkt.tau)
    for k in range(1, settings.max_steps + 1):
        if m > tau:
            y_next, *scalars = kkt.newton_mu_call(y, p, m)
        else:
            y_next, *scalars = kkt.newton_call(y, p)
        res0, res, f, h_max, mu_min, h0_max = (float(v) for v in scalars)
        if not (h0_max < 0 and h_max < 0 and mu_min > 0 and np.isfinite(res)):
            return None
        y = np.asarray(y_next).reshape(-1)
        if m <= tau:
            if res <= tol:
                return y, f, k
        elif res <= settings.kappa * m:
            m = max(tau, min(m / 5, m**1.5))
    return None


def cold_start(
    kkt: KKTSystem, w0: np.ndarray, p: np.ndarray, settings: Continuation
) -> np.ndarray | None:
    """The start ``y`` of the continuation from the cold guess ``w0`` on the central path at
    ``settings.m0``: multipliers 1 (equalities 0), re-centred by :func:`recentre`, then every
    ``mu = m0 / -H``; None when a row that no slack relaxes is not strictly interior."""
    lam, mu = np.zeros(kkt.neq), np.ones(kkt.nH)
    y = recentre(kkt, w0, lam, mu, p, settings)
    if y is None:
        return None
    H = kkt.rows_call(y[: kkt.nw], p)[0].reshape(-1)
    y[kkt.nw + kkt.neq :] = settings.m0 / np.maximum(-H, 1e-300)
    return y


def cold_continuation(
    kkt: KKTSystem,
    w0: np.ndarray,
    p: np.ndarray,
    tol: float,
    settings: Continuation,
    barriers: tuple[float, ...] = COLD_BARRIERS,
) -> tuple[np.ndarray, float, int] | None:
    """The continuation from the primal point ``w0`` (the cold guess; or the shifted plan,
    with ``(RESTART_BARRIER,)``) put on the central path (:func:`cold_start`) at each barrier
    parameter of ``barriers`` in turn: the first root found, as :func:`continuation` returns
    it (the steps of that attempt); None when none gets there."""
    for m0 in barriers:
        at = replace(settings, m0=m0)
        y = cold_start(kkt, w0, p, at)
        got = None if y is None else continuation(kkt, y, p, tol, at)
        if got is not None:
            return got
    return None
