"""Learners behind one propose/observe interface: MPC-RL, BO and MPC-RL-MOBO."""

from mpcmobo.learners.base import EpisodeResult, Learner, episode_result
from mpcmobo.learners.bo import BOLearner, HybridLearner, MOBOLearner
from mpcmobo.learners.mpc_rl import MPCRL
from mpcmobo.learners.registry import LEARNER_SPECS, LEARNERS, LearnerSpec, make_learner

__all__ = [
    "LEARNERS",
    "LEARNER_SPECS",
    "MPCRL",
    "BOLearner",
    "HybridLearner",
    "MOBOLearner",
    "EpisodeResult",
    "Learner",
    "LearnerSpec",
    "episode_result",
    "make_learner",
]
