"""Closed-loop episode records: what one episode on the plant leaves behind."""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import numpy as np


@dataclass
class EpisodeRecord:
    """Everything the learners need from one closed-loop episode of ``T`` steps.

    Index ``k`` runs over the plant's sampling instants. ``x``, ``V`` and ``dV`` have one more row
    than the inputs because the MPC is also solved at the final state ``x_T`` so that the temporal
    differences ``L_k + gamma V(x_{k+1}) - V(x_k)`` exist for every step. Where a solve failed the
    MPC quantities (``V``, ``dpi``, ``dV``) of that step are NaN and ``success`` is False.
    """

    x: np.ndarray  # (T+1, nx) plant states x_0..x_T
    u: np.ndarray  # (T, nu) applied inputs (policy + exploration, clipped to the bounds)
    pi: np.ndarray  # (T, nu) MPC policy pi_theta(x_k) (the fallback input where the solve failed)
    V: np.ndarray  # (T+1,) V_theta(x_k)
    dpi: np.ndarray  # (T, n_theta, nu) grad_theta pi_theta(x_k)
    dV: np.ndarray  # (T+1, n_theta) grad_theta V_theta(x_k)
    L: np.ndarray  # (T,) RL stage cost L(x_k, u_k)
    violation: np.ndarray  # (T,) constraint violation of (x_k, u_k) on the plant
    slack: np.ndarray  # (T,) sum of the MPC's slack variables
    success: np.ndarray  # (T+1,) bool, solver success of each solve
    theta: np.ndarray  # (n_theta,) parameters used during the episode
    gamma: float  # discount factor of the MPC and of the RL objective
    status: list[str] = field(default_factory=list)  # solver status of each solve
    solve_time: np.ndarray | None = None  # (T+1,) wall time of each solve (incl. sensitivities)

    @property
    def steps(self) -> int:
        """Number of time steps T."""
        return int(self.u.shape[0])

    @property
    def failures(self) -> int:
        """Number of failed MPC solves."""
        return int(np.count_nonzero(~self.success))

    def to_dict(self) -> dict:
        """The record as a dictionary of its fields."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_dict(cls, d: dict) -> EpisodeRecord:
        """The record from a dictionary of its fields."""
        return cls(**d)
