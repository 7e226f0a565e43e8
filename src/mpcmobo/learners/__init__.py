"""Learners behind one propose/observe interface: identify, MPC-RL, BO, MPC-RL-MOBO and the hybrid."""

from mpcmobo.learners.base import EpisodeResult, Learner, Replay, Starts, episode_result
from mpcmobo.learners.gp import BOLearner
from mpcmobo.learners.mobo import HybridLearner, MOBOLearner
from mpcmobo.learners.mpc_rl import MPCRL
from mpcmobo.learners.options import (
    BOOptions,
    HybridOptions,
    MOBOOptions,
    MPCRLOptions,
)
from mpcmobo.learners.registry import LEARNER_SPECS, LEARNERS, LearnerSpec, make_learner

__all__ = [
    "LEARNERS",
    "LEARNER_SPECS",
    "MPCRL",
    "BOLearner",
    "BOOptions",
    "EpisodeResult",
    "HybridLearner",
    "HybridOptions",
    "Learner",
    "LearnerSpec",
    "MOBOLearner",
    "MOBOOptions",
    "MPCRLOptions",
    "Replay",
    "Starts",
    "episode_result",
    "make_learner",
]
