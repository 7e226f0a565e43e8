"""One declared interface for every learner: :class:`Learner`.

A learner is built with its options (one typed object, :mod:`mpcmobo.learners.options`) and
the study's start design (:class:`Starts`: cycled or random initial states), and never
changes its configuration afterwards; what it learns lives in attributes with a trailing
underscore and is what :meth:`Learner.state_dict` saves. Every optional ability is a method
of :class:`Learner` with a documented default, which the loop, the job and the tuner call
unconditionally (docs/architecture.md, "The learner contract").
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable, Collection
from dataclasses import dataclass
from typing import Literal

import numpy as np

from mpcmobo.identify import Identification
from mpcmobo.learners.episode import (
    EpisodeResult,
    Replay,
    episode_result,
    replays_from_state,
    replays_state,
)
from mpcmobo.learners.prediction import StartCosts, Twin
from mpcmobo.systems.space import SearchSpace

__all__ = [
    "EpisodeResult",
    "Learner",
    "Progress",
    "Replay",
    "Starts",
    "check_choice",
    "episode_result",
    "replays_from_state",
    "replays_state",
]

# what long work reports as it goes: (what, done, total)
Progress = Callable[[str, int, int], None]


def check_choice(name: str, value: object, choices: Collection[str]) -> str:
    """``value`` when it is one of ``choices``; else a ``ValueError`` naming the option
    ``name``, its choices and the value given."""
    if value not in choices:
        raise ValueError(
            f"{name} must be one of {', '.join(repr(k) for k in choices)}, got {value!r}"
        )
    return str(value)


@dataclass(frozen=True)
class Starts:
    """How a study's episodes start: ``"cycle"`` through ``n_starts`` fixed seeded initial
    states (episode ``k`` from start ``k mod n_starts``, so candidates are compared from common
    starts) or ``"random"``, a fresh draw per episode (the paper's setting)."""

    mode: Literal["cycle", "random"] = "random"
    n_starts: int = 1

    def __post_init__(self) -> None:
        if self.mode not in ("cycle", "random"):
            raise ValueError(f"start mode must be 'cycle' or 'random', got {self.mode!r}")
        if int(self.n_starts) < 1:
            raise ValueError(f"n_starts must be at least 1, got {self.n_starts}")


class Learner(ABC):
    """A learner of the MPC parameters theta over a declared :class:`SearchSpace`.

    The loop is ``theta = learner.propose(); ...run an episode (with exploration noise unless
    learner.explores() is False)...; learner.observe(theta, result)``. Work (a fit, the twin's
    tuning) happens in :meth:`propose` and :meth:`observe`, and reports through the callback of
    :meth:`use_progress` where it is long. The queries (:meth:`incumbent`, :meth:`explores`,
    :meth:`learns_in_simulation`, :meth:`uses_start_cost`, :meth:`start_model`,
    :meth:`identified`, :meth:`identification`) are cheap and change nothing.
    :meth:`incumbent` is the deployed theta: what the plant runs outside learning and what
    J_eval measures.

    ``state_dict()`` holds the whole learned state (random generators included) as plain Python
    and NumPy objects, and ``load_state_dict`` restores it into a learner built with the same
    configuration, so that the next proposal is exactly the same.
    """

    name: str = "learner"

    def __init__(
        self, space: SearchSpace, theta0: np.ndarray, seed: int = 0, *, starts: Starts | None = None
    ) -> None:
        self.space = space
        self.theta0 = space.clip(np.asarray(theta0, dtype=float))
        self.seed = int(seed)
        self.starts = Starts() if starts is None else starts
        self.rng = np.random.default_rng(self.seed)
        self.n_observed = 0
        self.progress: Progress | None = None

    def theta_of(self, z: np.ndarray) -> np.ndarray:
        """The theta of the unit-cube point ``z``: exactly theta0 at theta0's own point (its
        round trip through ``z`` moves it by about 1e-12, which J_eval on the CSTR can tell)."""
        if np.array_equal(z, self.space.to_unit(self.theta0)):
            return self.theta0.copy()
        return self.space.from_unit(z, base=self.theta0)

    # ------------------------------------------------------------------ the loop
    @abstractmethod
    def propose(self) -> np.ndarray:
        """The next theta to run (full vector, inside the bounds)."""

    @abstractmethod
    def observe(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """Take the result of the episode run with ``theta``."""

    def observe_simulated(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """Take the result of an episode of ``theta`` simulated on the identified model in
        place of a plant episode the exploration budget refused (the plant ran the deployed
        theta, which :meth:`observe` takes next). It is evidence for the search, never for a
        deployment or an identification. Called only where :meth:`learns_in_simulation` says
        so; default: ignored."""
        return

    def observe_refused(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """Take a candidate ``theta`` the exploration budget refused where no simulation stands
        in for it (the model's error is too large for one): ``result`` is the deployed theta's
        plant episode from the same start (which :meth:`observe` takes next), its ``spread``
        the budget's bound on the candidate's cost there as a multiple of that episode's. The
        identifying learners judge their candidate on it under cycled starts
        (:meth:`~mpcmobo.learners.switch.ModelSwitch.refused`); default: ignored."""
        return

    # ------------------------------------------------------------------ queries
    @abstractmethod
    def incumbent(self) -> np.ndarray:
        """The deployed theta."""

    def verifying(self) -> np.ndarray | None:
        """The candidate theta whose episodes the learner is gathering before it decides to
        deploy it or not (default None: none); what ``Tuner.status`` calls *under
        verification*."""
        return None

    def explores(self) -> bool:
        """Whether the episode of the last proposal runs with the exploration noise (default
        True). A learner may ask for a noise-free episode to measure a theta (MPC-RL's
        verification blocks); such an episode has no critic, so no gradient."""
        return True

    def learns_in_simulation(self) -> bool:
        """Whether :meth:`observe_simulated` learns from a refused candidate's simulated
        episode (default False: the loop does not simulate it)."""
        return False

    def uses_start_cost(self) -> bool:
        """Whether the learner reads ``EpisodeResult.start_cost`` (default False): theta0's
        closed loop from the episode's initial state on the MPC's own model
        (:func:`~mpcmobo.mpc.model_rollout`), which the loop then computes for every episode
        (once per distinct start). It costs no plant episode, and it predicts how costly the
        start is whatever theta runs (the deployment tests' covariate under random starts)."""
        return False

    def start_model(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The controller and model of the start covariate, ``(theta, model parameters)``
        (default None: the learner's theta0 on the MPC's nominal model)."""
        return None

    def judge_starts(self) -> np.ndarray | None:
        """The initial states (n, nx) on which the learner's deployment test measures a theta
        on its model (the twin's simulated starts, where a twin judges), so that whoever asks
        what a theta would save (the exploration budget's payback) asks it where the
        deployment is decided (default None: the learner judges on plant episodes alone)."""
        return None

    def identified(self) -> np.ndarray | None:
        """The model parameters the learner has identified from the plant (default None: it
        does not identify, or has no fit yet)."""
        return None

    def identification(self) -> Identification | None:
        """The last fit of the model to the plant's transitions, with the parameters' standard
        deviations and the held-out one-step errors (default None: the learner does not
        identify, or has no fit yet)."""
        return None

    # ------------------------------------------------------------------ services and abilities
    def use_start_costs(self, costs: StartCosts) -> None:
        """Take the loop's closed-loop service (costs of a theta on a model from given starts),
        called once when the run is built. Default: not used. The identifying learners use it
        for the start covariate, the twin's tuning and its judgement."""
        return

    def use_progress(self, progress: Progress | None) -> None:
        """Report long work (the twin's tuning) to ``progress(what, done, total)``; None: to
        nobody (the default)."""
        self.progress = progress

    def seed_with(self, episodes: list[tuple[np.ndarray, EpisodeResult]]) -> None:
        """Take episodes run before the learner was built (identify-first's episodes of the
        learner's theta0) as evidence, before the first proposal. Default: ignored."""
        return

    def use_twin(self, twin: Twin) -> None:
        """Let ``twin`` (the closed loop on the deployed identified model) judge the learner's
        deployments. Default: ignored (a learner without deployment tests)."""
        return

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """The learner's state (name, seed, random stream, observations); the constructor owns the
        configuration."""
        return {
            "name": self.name,
            "seed": self.seed,
            "rng": self.rng.bit_generator.state,
            "n_observed": self.n_observed,
        }

    def _check_name(self, state: dict) -> None:
        """A ``ValueError`` unless ``state`` is of a learner of this name and seed."""
        if state.get("name") != self.name:
            raise ValueError(f"state of learner '{state.get('name')}' given to '{self.name}'")
        if int(state["seed"]) != self.seed:
            raise ValueError(
                f"state of a learner of seed {state['seed']} given to one of seed {self.seed}"
            )

    def load_state_dict(self, state: dict) -> None:
        """Continue from a :meth:`state_dict` of a learner of the same name and seed."""
        self._check_name(state)
        self.rng = np.random.default_rng()
        self.rng.bit_generator.state = state["rng"]
        self.n_observed = int(state["n_observed"])
