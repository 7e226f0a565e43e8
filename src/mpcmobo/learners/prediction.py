"""The twin as a predictor: the closed loop on an identified model, run by the loop's
closed-loop service (:data:`StartCosts`), predicts a plant episode from its initial state with
the episode's exploration replayed, and a theta's mean cost over simulated starts
(:class:`Twin`). The deployment judge reads these predictions
(:func:`~mpcmobo.learners.confidence.twin_confidence`)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import numpy as np

from mpcmobo.learners.episode import Replay
from mpcmobo.systems.base import System

__all__ = ["JUDGE_STARTS", "StartCosts", "Twin"]

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
