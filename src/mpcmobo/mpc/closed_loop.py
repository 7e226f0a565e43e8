"""Closed-loop episodes: the MPC's policy driving the plant, with exploration.

The plant is a ``gymnasium.Env`` (:mod:`mpcmobo.systems.plant`): the loop calls
``reset(seed=..., options={"x0": x0})`` and ``step(u)``, reads the measured state from the
observation and the stage cost and constraint violation from ``info`` (``"stage_cost"``,
``"violation"``; missing keys are computed with the system's model of them). Without a plant,
the system's own equations with ``true_params`` are the plant.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Any, Protocol

import gymnasium
import numpy as np

from mpcmobo.mpc.parametric import ParametricMPC
from mpcmobo.mpc.records import EpisodeRecord
from mpcmobo.mpc.solve import MPCSolution
from mpcmobo.systems.base import System
from mpcmobo.systems.plant import SystemPlant

RUNAWAY = 100.0  # a state this many x_scale from x_ref has run away: the episode is stopped


class PlantDiverged(FloatingPointError):
    """The plant diverged or ran away (``RUNAWAY``) at ``step``: the episode is stopped there.
    ``violation`` is the plant's summed constraint violation over the steps it ran, up to and
    including ``step``, what the plant went through before it was stopped."""

    def __init__(self, message: str, step: int, violation: float) -> None:
        super().__init__(message)
        self.step = int(step)
        self.violation = float(violation)


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
    plant: gymnasium.Env | None = None,
    plant_seed: int | None = None,
    noise: np.ndarray | None = None,
) -> EpisodeRecord:
    """Run ``steps`` closed-loop steps from ``x0`` and record what the learners need.

    ``plant``: the environment (default: the system's equations with ``true_params``), reset
    with ``seed=plant_seed`` and ``options={"x0": x0}`` (``x0`` None: the environment draws
    the start). At every step the MPC is solved at the measured state; its first input (or, if
    the solve failed, the safe fallback of :meth:`ParametricMPC.fallback_action`) plus the
    exploration noise (``noise`` (steps, nu) drawn beforehand, else ``exploration`` sampled
    with ``rng`` step by step), clipped to the input bounds, is applied to the plant. The MPC is solved
    once more at the final state so that ``V(x_T)`` exists. A failed solve never ends the
    episode; a plant that terminates ends it early (the record is shortened); a plant that
    diverges (a state not finite, or ``RUNAWAY`` x_scale from x_ref) is stopped at once with a
    :class:`PlantDiverged` (a ``FloatingPointError``) naming the step and the state and
    carrying the violation so far (a failed episode for the study).
    """
    steps = int(system.episode_steps if steps is None else steps)
    if steps < 1:
        raise ValueError(f"an episode needs at least one step, got {steps}")
    theta = mpc.check_theta(theta)
    if exploration is not None and rng is None and noise is None:
        raise ValueError("exploration noise needs a random generator (rng)")
    if noise is not None and np.shape(noise) != (steps, system.nu):
        raise ValueError(f"noise must be ({steps}, {system.nu}), got {np.shape(noise)}")
    plant = SystemPlant(system) if plant is None else plant
    options = None if x0 is None else {"x0": system.check_state(x0)}
    obs, _ = plant.reset(seed=plant_seed, options=options)
    x = _measured(system, obs, "reset")
    rec = _blank_record(steps, system.nx, system.nu, theta, mpc.gamma)
    mpc.reset()
    for k in range(steps + 1):
        rec.x[k] = x
        sol = mpc.solve(x, theta, sensitivities=sensitivities)
        _record_solve(rec, k, sol, sensitivities)
        if k == steps:
            break
        if noise is not None:
            u = sol.action + noise[k]
        elif exploration is not None:
            u = sol.action + exploration.sample(rng, k)  # type: ignore[arg-type]  # checked above
        else:
            u = sol.action
        x, terminated = _apply(system, plant, rec, k, x, system.clip_input(u))
        if terminated:
            steps = k + 1  # solve once more at the last state, then shorten the record
    if rec.steps > steps:
        _shorten(rec, steps)
    return rec


def model_plant(
    system: System, mpc: ParametricMPC, params: np.ndarray | None = None
) -> SystemPlant:
    """The MPC's own prediction model (its nominal ``model_params``, or ``params``) as a
    plant: the system's equations with those parameters. Building it builds the system's
    CasADi step function again, so a caller that runs many model episodes builds it once
    (:func:`model_rollout`'s ``plant``)."""
    p = mpc.model_params if params is None else params
    return SystemPlant(replace(system, true_params=np.asarray(p, dtype=float)))


def model_rollout(
    system: System,
    mpc: ParametricMPC,
    theta: np.ndarray | None,
    x0: np.ndarray,
    steps: int | None = None,
    plant: gymnasium.Env | None = None,
    noise: np.ndarray | None = None,
) -> EpisodeRecord:
    """The closed loop of ``theta`` from ``x0`` on the MPC's own prediction model instead of the
    plant (``plant``: :func:`model_plant`, built here if not given): noise-free, without
    sensitivities. What the model predicts of an episode from ``x0``, at no cost to the plant;
    with theta0 it is the learners' start covariate (``EpisodeResult.start_cost``)."""
    plant = model_plant(system, mpc) if plant is None else plant
    return rollout(system, mpc, theta, x0, steps, sensitivities=False, plant=plant, noise=noise)


def replay(
    system: System,
    mpc: ParametricMPC,
    theta: np.ndarray | None,
    states: np.ndarray,
    inputs: np.ndarray,
    stage_costs: np.ndarray | None = None,
    violations: np.ndarray | None = None,
) -> EpisodeRecord:
    """The record of an episode that ran elsewhere (a real plant): the MPC solved again on the
    logged ``states`` (T+1, nx), in order and warm-started as in :func:`rollout` (the MPC is
    deterministic given x and theta, so its actions, values and sensitivities are those it
    had), with the ``inputs`` (T, nu) actually applied; the stage costs and violations are
    the system's where not given (T,)."""
    theta = mpc.check_theta(theta)
    X, U = np.asarray(states, float), np.asarray(inputs, float)
    steps = U.shape[0]
    rec = _blank_record(steps, system.nx, system.nu, theta, mpc.gamma)
    mpc.reset()
    for k in range(steps + 1):
        x = system.check_state(X[k])
        rec.x[k] = x
        _record_solve(rec, k, mpc.solve(x, theta), True)
        if k == steps:
            break
        u = U[k]
        rec.u[k] = u
        rec.L[k] = system.stage_cost(x, u) if stage_costs is None else float(stage_costs[k])
        rec.violation[k] = (
            system.constraint_violation(x, u) if violations is None else float(violations[k])
        )
    return rec


def _measured(system: System, obs: Any, where: str) -> np.ndarray:
    """The state in the plant's observation (a copy; NaN or inf is a diverged plant)."""
    x = np.array(obs, dtype=float).reshape(-1)
    if x.shape != (system.nx,):
        raise ValueError(
            f"the plant's observation after {where} has {x.size} entries, the model "
            f"'{system.name}' has {system.nx} states"
        )
    return x


def _shorten(rec: EpisodeRecord, steps: int) -> None:
    """Keep the first ``steps`` steps of a record (a plant that terminated early)."""
    for name in ("u", "pi", "dpi", "L", "violation", "slack"):
        setattr(rec, name, getattr(rec, name)[:steps])
    for name in ("x", "V", "dV", "success", "solve_time"):
        setattr(rec, name, getattr(rec, name)[: steps + 1])


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
    rec.success[k], rec.solve_time[k] = sol.success, sol.solve_time  # type: ignore[index]  # set by _blank_record
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


def not_finite(k: int, x: np.ndarray) -> str:
    """Why an episode whose plant returned the state ``x``, not finite, after step ``k`` is
    stopped."""
    return (
        f"the plant returned a state that is not finite at step {k}: {x} (a sensor dropout, "
        "or a diverged simulation); the episode is stopped"
    )


def _apply(
    system: System, plant: gymnasium.Env, rec: EpisodeRecord, k: int, x: np.ndarray, u: np.ndarray
) -> tuple[np.ndarray, bool]:
    """Apply ``u`` at ``x`` on the plant: record u_k, L(x_k, u_k), the violation; x_{k+1} and
    whether the plant terminated."""
    rec.u[k] = u
    obs, _, terminated, _, info = plant.step(u)
    L, violation = info.get("stage_cost"), info.get("violation")
    rec.L[k] = system.stage_cost(x, u) if L is None else float(L)
    rec.violation[k] = system.constraint_violation(x, u) if violation is None else float(violation)
    x = _measured(system, obs, f"step {k}")
    stopped = None
    if not np.all(np.isfinite(x)):
        stopped = not_finite(k, x)
    else:
        far = np.abs(x - system.x_ref) > RUNAWAY * np.asarray(system.x_scale, float)
        if np.any(far):
            names = ", ".join(n for n, f in zip(system.state_names, far) if f)
            stopped = (
                f"the plant ran away at step {k}: state {x} ({names} more than {RUNAWAY:g} "
                "x_scale from x_ref); the episode is stopped"
            )
    if stopped is not None:
        raise PlantDiverged(stopped, k, float(np.sum(rec.violation[: k + 1])))
    return x, bool(terminated)
