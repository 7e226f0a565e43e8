"""Learners by name."""

from __future__ import annotations

import numpy as np

from mpcmobo.learners.base import Learner
from mpcmobo.learners.bo import BOLearner, HybridLearner, MOBOLearner
from mpcmobo.learners.mpc_rl import MPCRL
from mpcmobo.systems.space import SearchSpace

LEARNERS: dict[str, type[Learner]] = {
    "mpc-rl": MPCRL,
    "bo": BOLearner,
    "mobo": MOBOLearner,
    "hybrid": HybridLearner,
}


def make_learner(
    name: str, space: SearchSpace, theta0: np.ndarray, seed: int = 0, **options
) -> Learner:
    """Build the learner ``name`` ("mpc-rl", "bo", "mobo", "hybrid") with its options."""
    if name not in LEARNERS:
        raise ValueError(f"unknown learner '{name}'; available: {', '.join(sorted(LEARNERS))}")
    return LEARNERS[name](space, theta0, seed, **options)
