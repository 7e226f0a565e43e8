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

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from mpcmobo.learners.base import EpisodeResult, Replay, Starts
from mpcmobo.learners.gp import BOLearner
from mpcmobo.learners.options import BOOptions, IncumbentDeploy
from mpcmobo.systems.base import System
from mpcmobo.systems.space import SearchSpace

__all__ = ["JUDGE_STARTS", "TWIN_EPISODES", "TWIN_STARTS", "Twin", "TwinResult", "tune_on_twin"]

TWIN_STARTS = 8  # initial states of a twin evaluation
TWIN_EPISODES = 30  # twin evaluations (the deployed theta's the first)
JUDGE_STARTS = 64  # simulated starts of the twin's judgement of a deployment

# the loop's covariate service: (starts (n, nx), theta, model parameters[, one start's
# exploration (T, nu)]) -> (n,) costs
StartCosts = Callable[..., np.ndarray]


@dataclass(frozen=True)
class Twin:
    """The closed loop on an identified model as a predictor of plant episodes: ``costs`` is
    the loop's closed-loop service (cached there), ``params`` the model's parameters,
    ``starts`` the simulated starts (``JUDGE_STARTS`` of them, drawn by :meth:`make`) and
    ``to_theta`` maps a learner's point (unit cube for the GP learners) to theta."""

    params: np.ndarray
    costs: StartCosts
    starts: np.ndarray
    to_theta: Callable[[np.ndarray], np.ndarray] | None = None

    @classmethod
    def make(cls, system: System, params: np.ndarray, costs: StartCosts, seed: int) -> Twin:
        """A twin of the model with ``params`` and its ``JUDGE_STARTS`` simulated starts, drawn
        from the system's distribution with the job's ``seed`` (a stream of their own)."""
        rng = np.random.default_rng(np.random.SeedSequence([int(seed), 13]))
        starts = np.array([system.sample_initial_state(rng) for _ in range(JUDGE_STARTS)])
        return cls(np.asarray(params, float).copy(), costs, starts)

    def on(self, to_theta: Callable[[np.ndarray], np.ndarray]) -> Twin:
        """The same twin judging points that ``to_theta`` maps to theta."""
        return replace(self, to_theta=to_theta)

    def _theta(self, z: np.ndarray) -> np.ndarray:
        return np.asarray(z, float) if self.to_theta is None else self.to_theta(z)

    def predict(self, z: np.ndarray, replays: Sequence[Replay | None]) -> np.ndarray:
        """The mean stage cost of ``z``'s closed loop on the model for each plant episode: from
        its initial state, with its exploration replayed; NaN where the replay is unknown or
        the closed loop fails."""
        out = np.full(len(replays), np.nan)
        nx = self.starts.shape[1]
        theta = self._theta(z)
        for i, r in enumerate(replays):
            if r is None:
                continue
            x0 = np.asarray(r.x0, float)
            if x0.shape != (nx,):
                raise ValueError(f"a replay's initial state has shape {x0.shape}, not ({nx},)")
            out[i] = self.costs(x0[None, :], theta, self.params, r.exploration)[0]
        return out

    def per_start(
        self,
        z: np.ndarray,
        rows: np.ndarray,
        starts: np.ndarray,
        costs: np.ndarray,
        replays: Sequence[Replay | None],
        common: list[int],
    ) -> tuple[np.ndarray, np.ndarray]:
        """Per start of ``common``, over the episodes ``rows`` of ``z`` that ran from it: their
        mean plant cost (``costs``) and the mean of the twin's predictions of them (their
        ``replays``); ``starts`` holds each episode's start."""
        y, p = [], []
        for s in common:
            at = rows[starts[rows] == s]
            y.append(float(np.mean(costs[at])))
            p.append(float(np.mean(self.predict(z, [replays[int(i)] for i in at]))))
        return np.asarray(y, float), np.asarray(p, float)

    def simulate(self, z: np.ndarray) -> np.ndarray:
        """``z``'s costs on the simulated starts (NaN where a closed loop fails)."""
        return self.costs(self.starts, self._theta(z), self.params)


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
) -> TwinResult:
    """``episodes`` evaluations of the ``bo`` learner from ``theta`` on the model with
    ``params`` (module docstring); a closed loop that fails makes its evaluation a failed one
    (the GP learners rule its theta out)."""
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
    return TwinResult(best, best_cost, base, episodes)
