"""What a study keeps, as types: episode rows, stored trajectories, job checkpoints, reference.

On disk these are plain pickled dicts and Parquet columns (layout in :mod:`storage`); each type
converts with ``to_dict`` / ``from_dict``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np


@dataclass(kw_only=True)
class EpisodeRow:
    """One row of ``episodes.parquet``: one learning episode of one job (the columns, in order).

    The objectives f1..f4 are those of the paper (eq. cl_perf, f2, f3, f4); ``J_tilde`` is f1;
    ``mean_stage_cost`` is the undiscounted mean of L over the episode; ``J_eval_incumbent`` is
    NaN where the job's evaluation schedule did not evaluate the incumbent and inf where the
    incumbent ran the plant away from an evaluation start (``error`` says how); ``start_cost`` is
    theta0's cost from the episode's start on the MPC's own model (NaN unless the learner used
    it); ``identified`` the model parameters identified so far (empty without identification).
    """

    learner: str
    seed: int
    episode: int
    theta: list[float]
    f1: float
    f2: float
    f3: float
    f4: float
    J_tilde: float
    mean_stage_cost: float
    mean_abs_A: float
    critic_ok: bool
    violation: float
    solver_failures: int
    x0: list[float]
    incumbent: list[float]
    J_eval_incumbent: float = math.nan  # set by the job (NaN: not evaluated)
    error: str
    mpc_time_s: float
    learner_time_s: float
    eval_time_s: float = math.nan  # set by the job
    # theta0's mean stage cost from x0 on the MPC's own model (EpisodeResult.start_cost), the
    # deployment tests' covariate; NaN where the learner did not use it (and in older files)
    start_cost: float = math.nan
    # the model parameters the learner has identified after the episode (empty: none)
    identified: list[float] = field(default_factory=list)
    # what the episode cost the plant (its mean stage cost) and its excess over the deployed
    # controller's cost from the same start with the same noise (0 where it ran the deployed
    # theta; measured on a simulated plant, predicted by the MPC's own model on a real one)
    plant_cost: float = math.nan
    excess_cost: float = math.nan
    # with an exploration budget: the episode's cost predicted before it ran (on the learner's
    # model of the plant, from its start with its noise; NaN: not predicted), and why the
    # learner's candidate was refused and the deployed theta ran instead ("": it was not),
    # and that candidate (empty: none)
    predicted_cost: float = math.nan
    refused: str = ""
    refused_theta: list[float] = field(default_factory=list)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> EpisodeRow:
        """The row from its dictionary (one row of ``episodes.parquet``)."""
        return cls(**d)

    def to_dict(self) -> dict[str, Any]:
        """The row as a dictionary, columns in the order of ``episodes.parquet``."""
        return {name: getattr(self, name) for name in ROW_FIELDS}


ROW_FIELDS = tuple(f.name for f in fields(EpisodeRow))


@dataclass(frozen=True)
class Trajectory:
    """States (T+1, nx) and inputs (T, nu) of one stored episode.

    ``phase``: "initial" / "perfect" (the reference's evaluation episodes of theta0 with the
    imperfect and the perfect model, episode -1), "learning" (a learning episode, start 0) or
    "final" (the evaluation episodes of the final incumbent); ``start`` indexes the initial state.
    """

    phase: str
    episode: int
    start: int
    x: np.ndarray
    u: np.ndarray

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Trajectory:
        """The trajectory from its dictionary."""
        return cls(d["phase"], d["episode"], d["start"], d["x"], d["u"])

    def to_dict(self) -> dict[str, Any]:
        """The trajectory as a dictionary (one row of ``trajectories.parquet``)."""
        return {
            "phase": self.phase,
            "episode": self.episode,
            "start": self.start,
            "x": self.x,
            "u": self.u,
        }


@dataclass
class Checkpoint:
    """What a job saves after every episode: everything needed to continue it exactly.

    ``state`` is the :class:`LearningRun` state (learner and random generators), ``eval_state``
    the :class:`EvaluationSchedule` state, ``episodes`` the budget the job was run with,
    ``schema`` the format it was written in (:data:`~mpcmobo.experiment.storage.CHECKPOINT_SCHEMA`:
    only a checkpoint of the current schema can be resumed; the rows of an older one are read).
    """

    learner: str
    seed: int
    state: dict
    rows: list[EpisodeRow]
    trajectories: list[Trajectory]
    eval_state: dict
    wall_time_s: float
    episodes: int
    done: bool
    schema: int = 2
    pending: dict | None = None  # a trial asked for and not yet told (the Tuner's)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Checkpoint:
        """The checkpoint from the plain dictionary stored in the file."""
        return cls(
            learner=d["learner"],
            seed=int(d["seed"]),
            state=d["state"],
            rows=[EpisodeRow.from_dict(r) for r in d["rows"]],
            trajectories=[Trajectory.from_dict(t) for t in d["trajectories"]],
            eval_state=dict(d["eval_state"]),
            wall_time_s=float(d["wall_time_s"]),
            episodes=int(d["episodes"]),
            done=bool(d["done"]),
            schema=int(d.get("schema", 1)),
            pending=d.get("pending"),
        )

    def to_dict(self) -> dict[str, Any]:
        """The checkpoint as the plain dictionary stored in the file."""
        return {
            "state": self.state,
            "rows": [r.to_dict() for r in self.rows],
            "trajectories": [t.to_dict() for t in self.trajectories],
            "eval_state": self.eval_state,
            "wall_time_s": self.wall_time_s,
            "episodes": self.episodes,
            "done": self.done,
            "pending": self.pending,
        }  # storage.save_checkpoint adds the schema, learner and seed

    @property
    def incumbent(self) -> np.ndarray | None:
        """The incumbent after the last episode (None before the first)."""
        return np.asarray(self.rows[-1].incumbent, dtype=float) if self.rows else None


@dataclass(frozen=True)
class TrainingReference:
    """The like-for-like reference of the training curve J~ (f1, eq. cl_perf) for one seed:
    f1 of ``len(J_tilde)`` episodes of the perfect-model MPC (theta0) from the same initial
    states ``x0`` and with the same exploration noise as the first episodes of every learner
    of that seed (:func:`mpcmobo.experiment.training_reference.training_reference`). Its mean
    is J~* of the seed."""

    seed: int
    J_tilde: list[float]
    x0: list[list[float]]

    @property
    def mean(self) -> float:
        """J~* of the seed: the mean f1 of its episodes (NaN if one diverged)."""
        return float(np.mean(self.J_tilde)) if self.J_tilde else math.nan

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrainingReference:
        """From :meth:`to_dict`'s plain dict."""
        return cls(int(d["seed"]), [float(v) for v in d["J_tilde"]], [list(x) for x in d["x0"]])

    def to_dict(self) -> dict[str, Any]:
        """A plain dict (stored in ``reference.pkl``)."""
        return {"seed": self.seed, "J_tilde": list(self.J_tilde), "x0": list(self.x0)}


@dataclass
class Reference:
    """The study-level reference (``reference.pkl``), computed once per study: J* (the
    perfect-model MPC with theta0), J_eval(theta0), their evaluation episodes and what the
    figures need to know about the system (``reference.system_info``). Without a reference model
    ``J_star`` is None and ``J_star_missing`` says why. ``training``: the like-for-like reference
    of the training curve, one :class:`TrainingReference` per seed (empty in runs made before it
    existed, or without a reference model)."""

    J_star: float | None
    J_initial: float
    theta0: np.ndarray
    system: dict
    trajectories: list[Trajectory] = field(default_factory=list)
    wall_time_s: float | None = None
    J_star_missing: str | None = None
    training: list[TrainingReference] = field(default_factory=list)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Reference:
        """The reference from its dictionary (``reference.pkl``)."""
        return cls(
            J_star=d["J_star"],
            J_initial=d["J_initial"],
            theta0=d["theta0"],
            system=d["system"],
            trajectories=[Trajectory.from_dict(t) for t in d.get("trajectories", [])],
            wall_time_s=d.get("wall_time_s"),
            J_star_missing=d.get("J_star_missing"),
            training=[TrainingReference.from_dict(t) for t in d.get("training", [])],
        )

    def to_dict(self) -> dict[str, Any]:
        """The reference as a dictionary (``reference.pkl``)."""
        return {
            "J_star": self.J_star,
            "J_initial": self.J_initial,
            "theta0": self.theta0,
            "system": self.system,
            "trajectories": [t.to_dict() for t in self.trajectories],
            "wall_time_s": self.wall_time_s,
            "J_star_missing": self.J_star_missing,
            "training": [t.to_dict() for t in self.training],
        }
