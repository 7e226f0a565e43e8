"""Closed-loop episodes: the MPC (eq. Policy) driving the true plant, with exploration."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from mpcmobo.mpc.parametric import MPCSolution, ParametricMPC
from mpcmobo.mpc.records import EpisodeRecord
from mpcmobo.systems.base import System


class Exploration(Protocol):
    """Exploration noise on the applied inputs (e.g. ``mpcmobo.rl.GaussianExploration``)."""

    def sample(self, rng: np.random.Generator, k: int) -> np.ndarray:
        """(nu,) noise added to the input of step ``k``."""


def rollout(
    system: System,
    mpc: ParametricMPC,
    theta: np.ndarray | None,
    x0: np.ndarray,
    steps: int | None = None,
    *,
    rng: np.random.Generator | None = None,
    exploration: Exploration | None = None,
    sensitivities: bool = True,
) -> EpisodeRecord:
    """Run ``steps`` closed-loop steps from ``x0`` and record what the learners need.

    At every step the MPC is solved at the plant state; its first input (or, if the solve
    failed, the safe fallback of :meth:`ParametricMPC.fallback_action`) plus the exploration
    noise, clipped to the input bounds, is applied to the true plant. The MPC is solved once more
    at the final state so that ``V(x_T)`` exists. A failed solve never ends the episode.
    """
    steps = int(system.episode_steps if steps is None else steps)
    if steps < 1:
        raise ValueError(f"an episode needs at least one step, got {steps}")
    theta = mpc.check_theta(theta)
    x = system.check_state(x0)
    if exploration is not None and rng is None:
        raise ValueError("exploration noise needs a random generator (rng)")
    rec = _blank_record(steps, system.nx, system.nu, theta, mpc.gamma)
    mpc.reset()
    for k in range(steps + 1):
        rec.x[k] = x
        sol = mpc.solve(x, theta, sensitivities=sensitivities)
        _record_solve(rec, k, sol, sensitivities)
        if k == steps:
            break
        u = sol.action if exploration is None else sol.action + exploration.sample(rng, k)  # type: ignore[arg-type]  # rng checked above
        x = _apply(system, rec, k, x, system.clip_input(u))
    return rec


def _blank_record(steps: int, nx: int, nu: int, theta: np.ndarray, gamma: float) -> EpisodeRecord:
    """An episode of ``steps`` steps to be filled in; MPC quantities NaN until a solve succeeds."""
    nth = theta.shape[0]
    return EpisodeRecord(
        x=np.empty((steps + 1, nx)),
        u=np.empty((steps, nu)),
        pi=np.empty((steps, nu)),
        V=np.full(steps + 1, np.nan),
        dpi=np.full((steps, nth, nu), np.nan),
        dV=np.full((steps + 1, nth), np.nan),
        L=np.empty(steps),
        violation=np.empty(steps),
        slack=np.full(steps, np.nan),
        success=np.zeros(steps + 1, bool),
        theta=theta.copy(),
        gamma=gamma,
        status=[],
        solve_time=np.zeros(steps + 1),
    )


def _record_solve(rec: EpisodeRecord, k: int, sol: MPCSolution, sensitivities: bool) -> None:
    """The solve at x_k: success, time, status, V_theta(x_k) and its gradients, pi_theta(x_k)."""
    rec.success[k], rec.solve_time[k] = sol.success, sol.solve_time  # type: ignore[index]  # None only in old records
    rec.status.append(sol.status)
    if sol.success:
        rec.V[k] = sol.value
        if sensitivities:
            rec.dV[k] = sol.dV_dtheta
            if k < rec.steps:
                rec.dpi[k] = sol.dpi_dtheta
    if k < rec.steps:
        rec.pi[k] = sol.action
        if sol.success:
            rec.slack[k] = sol.slack


def _apply(system: System, rec: EpisodeRecord, k: int, x: np.ndarray, u: np.ndarray) -> np.ndarray:
    """Apply ``u`` at ``x`` on the true plant: record u_k, L(x_k, u_k), the violation; x_{k+1}."""
    rec.u[k] = u
    rec.L[k] = system.stage_cost(x, u)
    rec.violation[k] = system.constraint_violation(x, u)
    x = system.plant_step(x, u)
    if not np.all(np.isfinite(x)):
        raise FloatingPointError(f"the plant diverged at step {k}: state {x}")
    return x
