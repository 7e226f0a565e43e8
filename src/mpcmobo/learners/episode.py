"""What one episode gives a learner: :class:`EpisodeResult` (the objectives f1..f4, the CDPG
gradient and the episode's states and inputs), and :class:`Replay`, what the twin replays to
predict a plant episode."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mpcmobo.mpc.records import EpisodeRecord
from mpcmobo.rl import CompatibleCritic, CriticResult, mean_stage_cost, objectives

__all__ = ["EpisodeResult", "Replay", "episode_result", "replays_from_state", "replays_state"]


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
    # an episode simulated on the identified model in place of a refused one: the factor (>= 1)
    # within which its costs are trusted as the plant's (exp of twice the RMS log error of the
    # model's predictions of plant episodes; inf: not calibrated); the deployed theta's plant
    # episode given for a refused candidate (Learner.observe_refused): the bound on the
    # candidate's cost as a multiple of this episode's; NaN: a plant episode
    spread: float = float("nan")

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
