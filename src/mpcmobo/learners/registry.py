"""Learners by name: one :class:`LearnerSpec` per learner carries everything the package knows
about it (class, label and colour in the figures, scheduling cost, whether the paper runs it).
Adding a learner is one entry in ``LEARNER_SPECS``."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mpcmobo.learners.base import Learner
from mpcmobo.learners.bo import BOLearner, HybridLearner, MOBOLearner
from mpcmobo.learners.mpc_rl import MPCRL
from mpcmobo.systems.space import SearchSpace


@dataclass(frozen=True)
class LearnerSpec:
    """One learner: its settings name, class, figure label and colour, its relative cost per
    episode (used only to start the slowest jobs first; measured in docs/benchmarks.md: the
    EHVI learners spend the most per episode, MPC-RL the least), and whether the paper's
    study runs it (the default ``learners`` of the settings)."""

    name: str
    cls: type[Learner]
    label: str
    color: str
    job_cost: int
    in_paper: bool


LEARNER_SPECS: dict[str, LearnerSpec] = {
    spec.name: spec
    for spec in (
        LearnerSpec("mpc-rl", MPCRL, "MPC-RL", "tab:green", job_cost=1, in_paper=True),
        LearnerSpec("bo", BOLearner, "BO", "grey", job_cost=3, in_paper=True),
        LearnerSpec("mobo", MOBOLearner, "MPC-RL-MOBO", "tab:red", job_cost=4, in_paper=True),
        LearnerSpec("hybrid", HybridLearner, "hybrid", "tab:purple", job_cost=4, in_paper=False),
    )
}
LEARNERS: dict[str, type[Learner]] = {name: spec.cls for name, spec in LEARNER_SPECS.items()}


def make_learner(
    name: str, space: SearchSpace, theta0: np.ndarray, seed: int = 0, **options
) -> Learner:
    """Build the learner ``name`` ("mpc-rl", "bo", "mobo", "hybrid") with its options."""
    if name not in LEARNERS:
        raise ValueError(f"unknown learner '{name}'; available: {', '.join(sorted(LEARNERS))}")
    return LEARNERS[name](space, theta0, seed, **options)
