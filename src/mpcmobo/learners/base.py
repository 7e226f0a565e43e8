"""One interface for every learner: propose the next theta, observe the finished episode.

A learner is built with its options (one typed object, :mod:`mpcmobo.learners.options`) and
the study's start design (:class:`Starts`: cycled or random initial states), and never
changes its configuration afterwards; what it learns lives in attributes with a trailing
underscore and is what :meth:`Learner.state_dict` saves.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Collection
from dataclasses import dataclass
from typing import Literal

import numpy as np

from mpcmobo.identify import Identification
from mpcmobo.mpc.records import EpisodeRecord
from mpcmobo.rl import CompatibleCritic, CriticResult, mean_stage_cost, objectives
from mpcmobo.systems.space import SearchSpace


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


@dataclass(frozen=True)
class Replay:
    """What the twin replays to predict a plant episode
    (:class:`~mpcmobo.learners.twin.Twin`): its initial state ``x0`` (nx,) and its
    ``exploration`` (T, nu), the inputs applied minus the MPC's (None: a noise-free closed
    loop)."""

    x0: np.ndarray
    exploration: np.ndarray | None = None

    def state_dict(self) -> dict:
        """The arrays, as copies."""
        e = None if self.exploration is None else np.array(self.exploration, float)
        return {"x0": np.array(self.x0, float), "exploration": e}

    @classmethod
    def from_state(cls, state: dict | np.ndarray | None) -> Replay | None:
        """A :meth:`state_dict` again; an array is an initial state alone (a state of 1.0),
        an empty array or None no replay."""
        if state is None:
            return None
        if isinstance(state, dict):
            e = state["exploration"]
            return cls(np.array(state["x0"], float), None if e is None else np.array(e, float))
        x0 = np.array(state, float)
        return cls(x0) if x0.size else None


def replays_state(replays: list[Replay | None]) -> list[dict | None]:
    """A list of replays as plain arrays (a learner's :meth:`Learner.state_dict`)."""
    return [None if r is None else r.state_dict() for r in replays]


def replays_from_state(states: list) -> list[Replay | None]:
    """:func:`replays_state` read back (see :meth:`Replay.from_state`)."""
    return [Replay.from_state(s) for s in states]


@dataclass
class EpisodeResult:
    """What a learner observes of one episode: the objectives f1..f4 and the CDPG gradient."""

    objectives: np.ndarray  # (4,) f1..f4 (NaN where undefined, e.g. a diverged episode)
    grad: np.ndarray  # (n_theta,) CDPG policy gradient (eq. DPG), zeros if the critic failed
    critic_ok: bool
    Vc: float = float("nan")  # sum_k V^nu(x_k), for f3 of the next episode
    mean_abs_advantage: float = float("nan")
    failures: int = 0  # failed MPC solves in the episode
    start_id: int = -1  # index of the initial state in a fixed cycled set; -1: a random start
    x0: np.ndarray | None = None  # the episode's initial state
    violation: float = float("nan")  # plant constraint violation summed over the episode
    stage_cost: float = float("nan")  # the plain (undiscounted) mean stage cost, as J_eval's
    # theta0's mean stage cost from x0 on the MPC's own model (NaN unless the learner asks for
    # it, Learner.uses_start_cost): how hard the start is, a covariate of the episode's cost
    start_cost: float = float("nan")
    states: np.ndarray | None = None  # (T+1, nx) the plant's states (None: the episode failed)
    inputs: np.ndarray | None = None  # (T, nu) the inputs applied
    exploration: np.ndarray | None = None  # (T, nu) the inputs applied minus the MPC's

    @property
    def replay(self) -> Replay | None:
        """What the twin replays to predict the episode (None: its initial state is
        unknown)."""
        if self.x0 is None:
            return None
        e = None if self.exploration is None else np.asarray(self.exploration, float)
        return Replay(np.asarray(self.x0, float), e)

    @property
    def f1(self) -> float:
        """The closed-loop cost f1 (eq. cl_perf)."""
        return float(self.objectives[0])

    @property
    def valid(self) -> bool:
        """Whether all four objectives are finite."""
        return bool(np.all(np.isfinite(self.objectives)))


def episode_result(
    record: EpisodeRecord,
    critic: CompatibleCritic,
    previous_Vc: float | None,
    beta: float = 1.0,
) -> tuple[EpisodeResult, CriticResult]:
    """Fit the compatible critic to a record and compute the four objectives of section 4."""
    cr = critic.fit(record)
    f = np.asarray(objectives(record, cr, previous_Vc, beta), dtype=float)
    res = EpisodeResult(
        objectives=f,
        grad=np.where(np.isfinite(cr.grad), cr.grad, 0.0) if cr.ok else np.zeros_like(cr.grad),
        critic_ok=bool(cr.ok),
        Vc=float(cr.Vc),
        mean_abs_advantage=float(cr.mean_abs_advantage),
        failures=record.failures,
        x0=np.asarray(record.x[0], dtype=float).copy(),
        violation=float(np.sum(record.violation)),
        stage_cost=mean_stage_cost(record),
        states=np.asarray(record.x, dtype=float),
        inputs=np.asarray(record.u, dtype=float),
        exploration=np.asarray(record.u, dtype=float) - np.asarray(record.pi, dtype=float),
    )
    return res, cr


class Learner(ABC):
    """A learner of the MPC parameters theta over a declared :class:`SearchSpace`.

    The loop is ``theta = learner.propose(); ...run an episode (with exploration noise unless
    learner.explores() is False)...; learner.observe(theta, result)``.
    ``incumbent()`` is the deployed theta: what the plant runs outside learning and what J_eval
    measures.
    ``state_dict()`` holds the whole state (random generators included) as plain Python and NumPy
    objects, and ``load_state_dict`` restores it so that the next proposal is exactly the same.
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

    def theta_of(self, z: np.ndarray) -> np.ndarray:
        """The theta of the unit-cube point ``z``: exactly theta0 at theta0's own point (its
        round trip through ``z`` moves it by about 1e-12, which J_eval on the CSTR can tell)."""
        if np.array_equal(z, self.space.to_unit(self.theta0)):
            return self.theta0.copy()
        return self.space.from_unit(z, base=self.theta0)

    @abstractmethod
    def propose(self) -> np.ndarray:
        """The next theta to run (full vector, inside the bounds)."""

    @abstractmethod
    def observe(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """Take the result of the episode run with ``theta``."""

    @abstractmethod
    def incumbent(self) -> np.ndarray:
        """The deployed theta."""

    def explores(self) -> bool:
        """Whether the episode of the last proposal runs with the exploration noise (default
        True). A learner may ask for a noise-free episode to measure a theta (MPC-RL's
        verification blocks); such an episode has no critic, so no gradient."""
        return True

    def identified(self) -> np.ndarray | None:
        """The model parameters the learner has identified from the plant (None: it does not
        identify, or has no fit yet)."""
        return None

    def identification(self) -> Identification | None:
        """The last fit of the model to the plant's transitions, with the parameters' standard
        deviations and the held-out one-step errors (None: the learner does not identify, or
        has no fit yet)."""
        return None

    def uses_start_cost(self) -> bool:
        """Whether the learner reads ``EpisodeResult.start_cost`` (default False): theta0's
        closed loop from the episode's initial state on the MPC's own model
        (:func:`~mpcmobo.mpc.model_rollout`), which the loop then computes for every episode
        (once per distinct start). It costs no plant episode, and it predicts how costly the
        start is whatever theta runs (the deployment tests' covariate under random starts)."""
        return False

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
        """A ``ValueError`` unless ``state`` is of a learner of this name."""
        if state.get("name") != self.name:
            raise ValueError(f"state of learner '{state.get('name')}' given to '{self.name}'")

    def load_state_dict(self, state: dict) -> None:
        """Continue from a :meth:`state_dict` of a learner of the same name."""
        self._check_name(state)
        self.seed = int(state["seed"])
        self.rng = np.random.default_rng()
        self.rng.bit_generator.state = state["rng"]
        self.n_observed = int(state["n_observed"])
