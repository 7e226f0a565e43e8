"""The plant as a gymnasium environment: what the closed loop talks to.

The closed loop (:func:`mpcmobo.mpc.rollout`) drives any ``gymnasium.Env`` whose observation is
the measured state (a ``Box`` of the model's ``nx`` states) and whose action is the input (a
``Box`` of its ``nu`` inputs), through ``reset(seed=..., options={"x0": x0})`` and ``step(u)``.
``info`` of a step carries ``"stage_cost"`` (the RL stage cost L(x_k, u_k)) and ``"violation"``
(the constraint violation of (x_k, u_k)); an environment without them is scored with the
model's :meth:`~mpcmobo.systems.System.stage_cost` and
:meth:`~mpcmobo.systems.System.constraint_violation` on what it observed.

:class:`SystemPlant` is the plant of a :class:`~mpcmobo.systems.System` (its equations with
``true_params``); ``import mpcmobo`` registers the paper's CSTR plant as ``mpcmobo/CSTR-v0``
(and the test bed as ``mpcmobo/LQ-v0``). A user's simulator, or an adapter to a real process, is
just another environment (``[system] plant = "module:make_env"`` in a study's settings).
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces
from numpy.typing import ArrayLike

from mpcmobo.systems.base import System, SystemDefinitionError


class SystemPlant(gymnasium.Env):
    """The true plant of ``system`` (its equations with ``true_params``), one step per period.

    ``reset(seed=..., options={"x0": x0})`` starts at ``x0`` (without it: a draw of the system's
    initial-state box with the environment's generator). The reward is ``-L(x_k, u_k)``; the
    episode never terminates (a study decides its length; ``gymnasium.make`` adds the system's
    ``episode_steps`` as ``max_episode_steps``).

    ``process_noise`` and ``measurement_noise`` (standard deviations per state, default none):
    Gaussian noise added to the next state by every step, and to what the plant reports (the
    observation; the stage cost and the violation are those of the true state). Both are drawn
    from the environment's generator, so a ``reset`` seed makes an episode reproducible.
    """

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(
        self,
        system: System | str = "cstr",
        *,
        process_noise: ArrayLike | None = None,
        measurement_noise: ArrayLike | None = None,
        **options: Any,
    ) -> None:
        if isinstance(system, str):
            from mpcmobo.systems.registry import get_system

            system = get_system(system, **options)
        if not system.has_true_plant:
            raise SystemDefinitionError(
                f"{system.name} has no true plant (true_params is None): its plant must be "
                "another environment"
            )
        self.system = system
        self.observation_space = spaces.Box(-np.inf, np.inf, (system.nx,), np.float64)
        self.action_space = spaces.Box(system.u_lb, system.u_ub, (system.nu,), np.float64)
        self.process_noise = _noise(process_noise, system, "process_noise")
        self.measurement_noise = _noise(measurement_noise, system, "measurement_noise")
        self._x: np.ndarray | None = None

    def _observe(self) -> np.ndarray:
        """The measured state: the true state plus measurement noise."""
        assert self._x is not None
        if self.measurement_noise is None:
            return self._x.copy()
        return self._x + self.measurement_noise * self.np_random.standard_normal(len(self._x))

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict]:
        """Start at ``options["x0"]`` if given, else at a draw of the initial-state distribution."""
        super().reset(seed=seed)
        x0 = (options or {}).get("x0")
        if x0 is None:
            x0 = self.system.sample_initial_state(self.np_random)
        self._x = self.system.check_state(x0).copy()
        return self._observe(), {}

    def step(self, action: ArrayLike) -> tuple[np.ndarray, float, bool, bool, dict]:
        """One period of the true plant; ``info`` carries ``stage_cost`` and ``violation``."""
        if self._x is None:
            raise RuntimeError("call reset() before step()")
        x, u = self._x, self.system.check_input(action)
        L = self.system.stage_cost(x, u)
        violation = self.system.constraint_violation(x, u)
        self._x = self.system.plant_step(x, u)
        if self.process_noise is not None:
            self._x = self._x + self.process_noise * self.np_random.standard_normal(len(self._x))
        terminated = not bool(np.all(np.isfinite(self._x)))
        return self._observe(), -L, terminated, False, {"stage_cost": L, "violation": violation}


def _noise(std: ArrayLike | None, system: System, label: str) -> np.ndarray | None:
    """A noise level per state (None: no noise; all zeros counts as none)."""
    if std is None:
        return None
    v = np.asarray(std, float).reshape(-1)
    if v.shape != (system.nx,) or not np.all(np.isfinite(v)) or np.any(v < 0):
        raise SystemDefinitionError(
            f"{label} must be {system.nx} standard deviations >= 0, one per state "
            f"({', '.join(system.state_names)}), got {np.asarray(std).tolist()}"
        )
    return None if not np.any(v > 0) else v


def check_plant(env: gymnasium.Env, system: System, label: str = "plant") -> None:
    """The plant's observation and action spaces match the model's states and inputs."""
    obs, act = getattr(env, "observation_space", None), getattr(env, "action_space", None)
    for space, n, what in ((obs, system.nx, "states"), (act, system.nu, "inputs")):
        kind = "observation" if what == "states" else "action"
        if not isinstance(space, spaces.Box):
            raise SystemDefinitionError(
                f"{label}: the {kind} space must be a gymnasium Box, got {type(space).__name__}"
            )
        if space.shape != (n,):
            raise SystemDefinitionError(
                f"{label}: the {kind} space has shape {space.shape}, but the model "
                f"'{system.name}' has {n} {what} ({', '.join(getattr(system, what[:-1] + '_names'))})"
            )


def check_reset(plant: gymnasium.Env, system: System, noise: ArrayLike | None = None) -> None:
    """That the plant starts where it is told (``reset(options={"x0": x0})``): on at least
    three of five draws of the initial states, within a quarter of their range (at least 5%
    and at most half of the state scale, and at least four standard deviations of the
    measurement ``noise``, per state). Thetas are compared from their episodes' starts, so a
    plant that ignores them makes every comparison meaningless."""
    scale = np.asarray(system.x_scale, float)
    spread = 0.25 * (np.asarray(system.x0_ub, float) - np.asarray(system.x0_lb, float))
    tol = np.minimum(0.5 * scale, np.maximum(spread, 0.05 * scale))
    tol = np.maximum(tol, 4 * np.asarray(noise if noise is not None else 0.0, float))
    rng = np.random.default_rng(0)
    off = []
    for _ in range(5):
        x0 = system.sample_initial_state(rng)
        obs = np.asarray(plant.reset(seed=0, options={"x0": x0})[0], float).reshape(-1)
        if obs.shape == x0.shape and np.any(np.abs(obs - x0) > tol):
            off.append((x0, obs))
    if len(off) >= 3:
        x0, obs = off[0]
        raise SystemDefinitionError(
            f"reset(options={{'x0': x0}}) did not start the plant at x0 "
            f"(asked {np.round(x0, 6).tolist()}, got {np.round(obs, 6).tolist()}; {len(off)} "
            "of 5 starts); a plant must start where options['x0'] says (docs/user-systems.md)"
        )
