"""Closed-loop episodes: the MPC (eq. Policy) driving the true plant, with exploration."""

from __future__ import annotations

from typing import Protocol

import numpy as np

from mpcmobo.mpc.parametric import ParametricMPC
from mpcmobo.mpc.records import EpisodeRecord
from mpcmobo.systems.base import System


class Exploration(Protocol):
    def sample(self, rng: np.random.Generator, k: int) -> np.ndarray: ...


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
    nx, nu, nth = system.nx, system.nu, mpc.n_theta
    X = np.empty((steps + 1, nx))
    U, PI = np.empty((steps, nu)), np.empty((steps, nu))
    V = np.full(steps + 1, np.nan)
    dPI = np.full((steps, nth, nu), np.nan)
    dV = np.full((steps + 1, nth), np.nan)
    L, viol, slack = np.empty(steps), np.empty(steps), np.full(steps, np.nan)
    success = np.zeros(steps + 1, bool)
    times = np.zeros(steps + 1)
    status: list[str] = []
    mpc.reset()
    for k in range(steps + 1):
        X[k] = x
        sol = mpc.solve(x, theta, sensitivities=sensitivities)
        success[k], times[k] = sol.success, sol.solve_time
        status.append(sol.status)
        if sol.success:
            V[k] = sol.value
            if sensitivities:
                dV[k] = sol.dV_dtheta
                if k < steps:
                    dPI[k] = sol.dpi_dtheta
        if k == steps:
            break
        PI[k] = sol.action
        u = sol.action if exploration is None else sol.action + exploration.sample(rng, k)
        u = system.clip_input(u)
        U[k] = u
        if sol.success:
            slack[k] = sol.slack
        L[k] = system.stage_cost(x, u)
        viol[k] = system.constraint_violation(x, u)
        x = system.plant_step(x, u)
        if not np.all(np.isfinite(x)):
            raise FloatingPointError(f"the plant diverged at step {k}: state {x}")
    return EpisodeRecord(
        x=X,
        u=U,
        pi=PI,
        V=V,
        dpi=dPI,
        dV=dV,
        L=L,
        violation=viol,
        slack=slack,
        success=success,
        theta=theta.copy(),
        gamma=mpc.gamma,
        status=status,
        solve_time=times,
    )
