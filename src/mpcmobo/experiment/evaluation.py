"""The evaluation protocol used wherever results are compared: J_eval(theta) and J*.

``J_eval(theta)`` is the mean, over a fixed seeded set of initial states, of the mean RL stage
cost of a ``T_f``-step closed-loop episode of the imperfect-model MPC with parameters ``theta``,
without exploration. ``J*`` is the same for the perfect-model MPC with ``theta0``: the closed-loop
performance the learning should reach (the blue dashed line of Fig. 1). A system without a
reference model has no J*: results are then relative to ``J_eval(theta0)`` (J_initial).
"""

from __future__ import annotations

import gymnasium
import numpy as np

from mpcmobo.experiment.build import build_plant, needs_plant
from mpcmobo.experiment.settings import Settings
from mpcmobo.mpc import EpisodeRecord, ParametricMPC, rollout, rollouts
from mpcmobo.rl.objectives import mean_stage_cost
from mpcmobo.systems.base import System
from mpcmobo.systems.plant import SystemPlant


def mean_cost(episodes: list[EpisodeRecord]) -> float:
    """The mean over episodes of each episode's mean stage cost: J_eval of their theta."""
    return float(np.mean([mean_stage_cost(r) for r in episodes]))


class Evaluator:
    """Deterministic closed-loop evaluation of theta on a fixed set of initial states."""

    def __init__(
        self,
        system: System,
        n_starts: int = 10,
        seed: int = 2025,
        steps: int | None = None,
        mpc_options: dict | None = None,
        plant: gymnasium.Env | None = None,
    ) -> None:
        if n_starts < 1:
            raise ValueError(f"the evaluation needs at least one initial state, got {n_starts}")
        self.system = system
        self.plant = plant  # None: the system's own equations
        self.steps = int(system.episode_steps if steps is None else steps)
        self.seed = int(seed)
        rng = np.random.default_rng(self.seed)
        self.starts = np.array([system.sample_initial_state(rng) for _ in range(n_starts)])
        self._mpc_options = dict(mpc_options or {})
        self._mpcs: dict[str, ParametricMPC] = {}
        self._cache: dict[tuple[str, bytes], float] = {}

    def mpc(self, model: str = "imperfect") -> ParametricMPC:
        """The evaluation MPC with ``model`` (built once, then reused)."""
        if model not in self._mpcs:
            self._mpcs[model] = ParametricMPC(self.system, model=model, **self._mpc_options)
        return self._mpcs[model]

    def episodes(self, theta: np.ndarray | None, model: str = "imperfect") -> list[EpisodeRecord]:
        """The evaluation episodes of ``theta`` (no exploration, no sensitivities); the first
        start's whose closed loop fails raises what it raised. On the system's own equations
        (or a noise-free :class:`~mpcmobo.systems.plant.SystemPlant`) the closed loops run
        together (:func:`mpcmobo.mpc.rollouts`: the same records), else one after the other."""
        mpc = self.mpc(model)
        plant = self.plant
        if plant is None or (
            type(plant) is SystemPlant and plant.process_noise is None is plant.measurement_noise
        ):
            system = self.system if plant is None else plant.system
            recs = rollouts(system, mpc, theta, self.starts, self.steps)
            for r in recs:
                if not isinstance(r, EpisodeRecord):
                    raise r
            return recs  # type: ignore[return-value]  # all records: checked above
        return [
            rollout(
                self.system,
                mpc,
                theta,
                x0,
                self.steps,
                sensitivities=False,
                plant=self.plant,
                plant_seed=self.plant_seed(i),
            )
            for i, x0 in enumerate(self.starts)
        ]

    def plant_seed(self, i: int) -> int:
        """The plant's seed of the ``i``-th evaluation start (the same for every theta)."""
        return int(np.random.SeedSequence([self.seed, 5, i]).generate_state(1)[0])

    def J_eval(self, theta: np.ndarray | None, model: str = "imperfect") -> float:
        """Mean over the fixed starts of the mean stage cost (cached per theta)."""
        theta = self.mpc(model).check_theta(theta)
        key = (model, theta.tobytes())
        if key not in self._cache:
            self._cache[key] = mean_cost(self.episodes(theta, model))
        return self._cache[key]

    def remember(self, theta: np.ndarray | None, value: float, model: str = "imperfect") -> None:
        """Store a J_eval computed elsewhere (e.g. from :meth:`episodes`) in the cache."""
        theta = self.mpc(model).check_theta(theta)
        self._cache[(model, theta.tobytes())] = float(value)

    def is_cached(self, theta: np.ndarray | None, model: str = "imperfect") -> bool:
        """Whether J_eval of ``theta`` with ``model`` is already computed."""
        theta = self.mpc(model).check_theta(theta)
        return (model, theta.tobytes()) in self._cache

    @property
    def has_J_star(self) -> bool:
        """Whether J* exists: the system has a reference (perfect) model."""
        return self.system.has_reference_model

    def J_star(self) -> float | None:
        """J*: the perfect-model MPC with theta0 on the same starts; None without a reference
        model (:func:`no_J_star_reason` says why)."""
        if not self.has_J_star:
            return None
        return self.J_eval(None, model="perfect")


def no_J_star_reason(system: System) -> str:
    """Why J* is absent for ``system`` (the value of ``J_star_missing`` in the records)."""
    return (
        f"the system '{system.name}' has no reference model (neither true_params nor "
        "models['perfect']), so there is no perfect-model MPC: results are relative to "
        "J_initial, the MPC with theta0"
    )


def make_evaluator(
    settings: Settings,
    system: System,
    plant: gymnasium.Env | None = None,
    *,
    n_starts: int | None = None,
    seed: int | None = None,
) -> Evaluator:
    """The evaluator of a study's settings (``[evaluation]``, the MPC options, the plant);
    ``n_starts`` and ``seed``, if given, in place of the settings' (e.g. fresh starts to
    recheck thetas on, apart from the evaluation's)."""
    ev = settings.evaluation
    return Evaluator(
        system,
        n_starts=ev.n_starts if n_starts is None else n_starts,
        seed=ev.seed if seed is None else seed,
        steps=ev.steps if ev.steps is not None else settings.steps,
        mpc_options=settings.mpc.options(),
        plant=build_plant(settings, system) if plant is None and needs_plant(settings) else plant,
    )
