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
    """

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(self, system: System | str = "cstr", **options: Any) -> None:
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
        self._x: np.ndarray | None = None

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict]:
        """Start at ``options["x0"]`` if given, else at a draw of the initial-state distribution."""
        super().reset(seed=seed)
        x0 = (options or {}).get("x0")
        if x0 is None:
            x0 = self.system.sample_initial_state(self.np_random)
        self._x = self.system.check_state(x0).copy()
        return self._x.copy(), {}

    def step(self, action: ArrayLike) -> tuple[np.ndarray, float, bool, bool, dict]:
        """One period of the true plant; ``info`` carries ``stage_cost`` and ``violation``."""
        if self._x is None:
            raise RuntimeError("call reset() before step()")
        x, u = self._x, self.system.check_input(action)
        L = self.system.stage_cost(x, u)
        violation = self.system.constraint_violation(x, u)
        self._x = self.system.plant_step(x, u)
        terminated = not bool(np.all(np.isfinite(self._x)))
        return self._x.copy(), -L, terminated, False, {"stage_cost": L, "violation": violation}


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
