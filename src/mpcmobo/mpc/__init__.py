"""The parametric MPC of eq. (V0), its sensitivities and closed-loop episodes."""

from mpcmobo.mpc.batch import rollouts
from mpcmobo.mpc.closed_loop import PlantDiverged, model_plant, model_rollout, replay, rollout
from mpcmobo.mpc.parametric import ParametricMPC
from mpcmobo.mpc.records import EpisodeRecord
from mpcmobo.mpc.solve import MPCSolution

__all__ = [
    "EpisodeRecord",
    "MPCSolution",
    "ParametricMPC",
    "PlantDiverged",
    "model_plant",
    "model_rollout",
    "replay",
    "rollout",
    "rollouts",
]
