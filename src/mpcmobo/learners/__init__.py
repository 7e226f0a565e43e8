"""Learners behind one propose/observe interface: identify, MPC-RL, BO, MPC-RL-MOBO and the hybrid.

The names are imported when first used (PEP 562): ``mpcmobo.learners.registry`` and
``mpcmobo.learners.options`` can be read without importing torch and BoTorch.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from mpcmobo.lazy import lazy_names

if TYPE_CHECKING:
    from mpcmobo.learners.base import EpisodeResult, Learner, Replay, Starts, episode_result
    from mpcmobo.learners.gp import BOLearner
    from mpcmobo.learners.mobo import HybridLearner, MOBOLearner
    from mpcmobo.learners.mpc_rl import MPCRL
    from mpcmobo.learners.options import BOOptions, HybridOptions, MOBOOptions, MPCRLOptions
    from mpcmobo.learners.registry import LEARNER_SPECS, LEARNERS, LearnerSpec, make_learner

_WHERE = {
    "EpisodeResult": "base",
    "Learner": "base",
    "Replay": "base",
    "Starts": "base",
    "episode_result": "base",
    "BOLearner": "gp",
    "HybridLearner": "mobo",
    "MOBOLearner": "mobo",
    "MPCRL": "mpc_rl",
    "BOOptions": "options",
    "HybridOptions": "options",
    "MOBOOptions": "options",
    "MPCRLOptions": "options",
    "LEARNER_SPECS": "registry",
    "LEARNERS": "registry",
    "LearnerSpec": "registry",
    "make_learner": "registry",
}

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


__getattr__, __dir__ = lazy_names(__name__, _WHERE, __all__)
