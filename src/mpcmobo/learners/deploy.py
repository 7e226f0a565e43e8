"""Which theta is deployed, and which are safe (issue 11, items 2-3).

The deployed theta (the incumbent, what J_eval measures) changes only when the learner's own
surrogate says a candidate is better in expectation over the initial states with probability
at least ``deploy_confidence``: ``P(J(new) < J(current)) >= deploy_confidence``, estimated
from joint posterior samples of the two expectations (common contexts, one joint posterior).
Candidates are the thetas the learner has run. A theta is *safe* when the
``safety_confidence`` quantile of its expected violation is at most the violation budget;
only safe candidates are deployed.

The default budget (``violation_budget = "auto"``) is relative to theta0 (safe by
assumption): ``2 x`` theta0's expected violation per episode over the contexts (the posterior
mean, re-estimated at every fit from all episodes) plus an absolute floor from the system's
state bounds (:class:`~mpcmobo.bo.context.ContextSpec`, 0.1% of the summed widths), so it is
scale-free. A first version set it from theta0's first episode alone; on the CSTR that
episode had no violation while theta0's expected violation is about 6, the budget (0.1) then
excluded every theta including theta0's neighbours, and the learner re-ran theta0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mpcmobo.bo.context import expected_outcome_samples
from mpcmobo.bo.surrogate import GPSurrogate

BUDGET_FACTOR = 2.0  # default budget: this multiple of theta0's own violation (+ floor)


@dataclass(frozen=True)
class DeployRule:
    """Options of the deployment and safety rules (see the module docstring)."""

    kappa: float = 1.0
    deploy_confidence: float | None = None
    safety_confidence: float = 0.9
    n_samples: int = 128

    def __post_init__(self) -> None:
        if self.deploy_confidence is not None and not 0.5 <= self.deploy_confidence < 1:
            raise ValueError(
                f"deploy_confidence must be in [0.5, 1) or None, got {self.deploy_confidence}"
            )
        if not 0.5 <= self.safety_confidence < 1:
            raise ValueError(f"safety_confidence must be in [0.5, 1), got {self.safety_confidence}")

    def safe(self, samples: np.ndarray, budget: float | None) -> np.ndarray:
        """(n,) True where the expected violation's upper quantile is within the budget
        (``samples`` (S, n, m): the violation is the last column)."""
        if budget is None:
            return np.ones(samples.shape[1], dtype=bool)
        ucb = np.quantile(samples[:, :, -1], self.safety_confidence, axis=0)
        return ucb <= budget

    def score(self, samples: np.ndarray) -> np.ndarray:
        """Risk-averse score of the expected f1 (first column): mean + kappa std."""
        f1 = samples[:, :, 0]
        return f1.mean(axis=0) + self.kappa * f1.std(axis=0)

    def choose(
        self,
        surrogate: GPSurrogate,
        Z: np.ndarray,
        current: np.ndarray,
        contexts: np.ndarray,
        budget: float | None,
        seed: int,
    ) -> np.ndarray:
        """The deployed unit-cube theta after a fit: ``current`` unless a safe observed theta
        in ``Z`` is confidently better (or ``deploy_confidence`` is None: the best safe one)."""
        Z = np.unique(np.atleast_2d(Z), axis=0)
        if len(Z) == 0:
            return current
        S = expected_outcome_samples(surrogate, Z, contexts, n_samples=self.n_samples, seed=seed)
        ok = self.safe(S, budget)
        if not ok.any():
            return current
        score = np.where(ok, self.score(S), np.inf)
        best = Z[int(np.argmin(score))]
        if np.array_equal(best, current):
            return current
        if self.deploy_confidence is None:
            return best.copy()
        J = expected_outcome_samples(
            surrogate,
            np.vstack([best, current]),
            contexts,
            n_samples=4 * self.n_samples,
            seed=seed + 1,
            joint=True,
        )[:, :, 0]
        p = float(np.mean(J[:, 0] < J[:, 1]))
        return best.copy() if p >= self.deploy_confidence else current


def default_budget(theta0_violation: float, floor: float) -> float:
    """``BUDGET_FACTOR x`` theta0's (expected) violation plus ``floor`` (non-finite: floor)."""
    v = float(theta0_violation)
    return BUDGET_FACTOR * (v if np.isfinite(v) and v > 0 else 0.0) + float(floor)
