"""Tune theta on the twin: the closed loop on the identified model, before the plant runs it.

Once identify-first has deployed an identified model, the MPC's cost, back-offs and learnable
model parameters can be tuned in simulation, where an episode costs a fraction of a second and
risks nothing. :func:`tune_on_twin` runs the ``bo`` learner (one GP on the cost, log expected
improvement, its trust region; the paper's incumbent rule, as the twin is noise-free) for
``TWIN_EPISODES`` evaluations from the deployed theta. An evaluation is the mean stage cost of
noise-free closed loops of the MPC on the identified model (the loop's start-cost service) from
``TWIN_STARTS`` initial states drawn from the system's distribution with the job's seed, never
the evaluation's. The cheapest theta seen is the result. The twin knows only the identified
model: where the model is right it finds what a better cost can do beyond it (the paper's
Theorem 1), where its structure is wrong it may not; so its theta goes to the plant as a
candidate of the model switch, deployed only on the evidence of its own plant episodes.

The twin also judges: a :class:`Twin` predicts any theta's plant episode from its initial
state with the episode's exploration replayed (the plant's own episode, where the model is
right), and its mean over ``JUDGE_STARTS`` simulated starts, for the deployment tests'
prediction-powered confidence (:func:`~mpcmobo.learners.confidence.twin_confidence`): a few
plant episodes then decide what the twin measures on many starts, as far as the plant
confirms the twin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mpcmobo.learners.base import Progress, Starts
from mpcmobo.learners.episode import EpisodeResult
from mpcmobo.learners.gp import BOLearner
from mpcmobo.learners.options import BOOptions, IncumbentDeploy
from mpcmobo.learners.prediction import JUDGE_STARTS, StartCosts, Twin
from mpcmobo.systems.space import SearchSpace

__all__ = [
    "JUDGE_STARTS",
    "TWIN_EPISODES",
    "TWIN_STARTS",
    "Progress",
    "StartCosts",
    "Twin",
    "TwinResult",
    "tune_on_twin",
]

TWIN_STARTS = 8  # initial states of a twin evaluation
TWIN_EPISODES = 30  # twin evaluations (the deployed theta's the first)


@dataclass(frozen=True)
class TwinResult:
    """The cheapest theta on the twin, its cost and the starting theta's (mean stage costs)."""

    theta: np.ndarray
    cost: float
    base_cost: float
    evaluations: int

    @property
    def better(self) -> bool:
        """Whether the twin found a theta cheaper than the one it started from."""
        return bool(np.isfinite(self.cost) and self.cost < self.base_cost)


def tune_on_twin(
    space: SearchSpace,
    theta: np.ndarray,
    params: np.ndarray,
    costs: StartCosts,
    starts: np.ndarray,
    seed: int,
    episodes: int = TWIN_EPISODES,
    progress: Progress | None = None,
) -> TwinResult:
    """``episodes`` evaluations of the ``bo`` learner from ``theta`` on the model with
    ``params`` (module docstring); a closed loop that fails makes its evaluation a failed one
    (the GP learners rule its theta out). ``progress`` hears ``("twin", k, episodes)`` after
    each evaluation."""
    learner = BOLearner(
        space, theta, seed, BOOptions(deploy=IncumbentDeploy()), starts=Starts("random")
    )
    zeros = np.zeros(len(theta))
    best, best_cost, base = np.asarray(theta, float).copy(), float("inf"), float("nan")
    for k in range(episodes):
        proposed = learner.propose()
        J = float(np.mean(costs(starts, proposed, params)))  # NaN if a closed loop failed
        result = EpisodeResult(np.array([J, 0.0, 0.0, 0.0]), zeros, True, stage_cost=J)
        learner.observe(proposed, result)
        if k == 0:
            base = J
        if np.isfinite(J) and J < best_cost:
            best, best_cost = np.asarray(proposed, float).copy(), J
        if progress is not None:
            progress("twin", k + 1, episodes)
    return TwinResult(best, best_cost, base, episodes)
