"""Reinforcement-learning pieces: compatible critic (LSTDV / LSTDQ), DPG gradient, the four
objectives f1..f4 and the exploration noise (paper, sections 2.2, 2.3 and 4)."""

from mpcmobo.rl.critic import (
    CompatibleCritic,
    CriticResult,
    lstd_solve,
    ridge_lstsq,
    transition_mask,
)
from mpcmobo.rl.exploration import GaussianExploration
from mpcmobo.rl.objectives import (
    f1_closed_loop_cost,
    f2_optimality,
    f3_critic_drift,
    f4_lyapunov,
    mean_stage_cost,
    objectives,
)

__all__ = [
    "CompatibleCritic",
    "CriticResult",
    "GaussianExploration",
    "f1_closed_loop_cost",
    "f2_optimality",
    "f3_critic_drift",
    "f4_lyapunov",
    "lstd_solve",
    "mean_stage_cost",
    "objectives",
    "ridge_lstsq",
    "transition_mask",
]
