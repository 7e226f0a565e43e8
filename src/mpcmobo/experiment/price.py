"""The price of exploration: which candidates run on the plant, and when tuning stops exploring.

Before an episode of a candidate theta runs (a theta other than the deployed one, with
exploration noise or without, as MPC-RL's verification of its iterate), the loop predicts its
cost from the coming start, with the episode's exploration noise replayed, on the learner's
best model of the plant (the identified model where the learner identifies one, else the
deployed theta's own model), and the deployed controller's cost from the same start with the
same noise
(:meth:`~mpcmobo.experiment.loop.LearningRun.plan`). :class:`ExplorationPrice` decides:

* the model's record is ``log(plant cost / predicted cost)`` over the episodes run so far (a
  new model is first checked on its predictions of the last :data:`RECENT` episodes); its
  error (:meth:`ExplorationPrice.error`) is their RMS, its *ratio error* ``s``
  (:meth:`ExplorationPrice.ratio_error`) their standard deviation: the rule compares two
  predictions of the same model from the same start, where a bias common to both (a
  structurally wrong model that under-predicts every closed loop by a factor) cancels; a
  candidate predicted at ``r`` times the deployed controller's cost may be ``r * exp(s)``;
* a candidate whose predicted ratio, so bounded, is more than ``1 + budget`` is **refused**:
  the deployed controller runs instead (with the same noise), and the learner observes that
  episode. Before the model has a record the
  bound is infinite: only the deployed controller runs;
* every other candidate runs. One predicted to cost more than the deployed controller
  **pays back** if, were it deployed, its predicted saving per episode (the deployed
  controller's mean cost less its own, noise-free on the model from the starts where the
  learner's deployment test measures a theta, the twin's, else from the run's fixed starts)
  plus, at best, the model's error (``exp(s) - 1`` times the deployed controller's mean cost)
  over the remaining episodes covers its predicted excess;
* where the model's error is at most :data:`SIMULATION_ERROR` and the learner learns in
  simulation (:meth:`~mpcmobo.learners.Learner.learns_in_simulation`), a candidate that is
  refused or does not pay back does not run either: the deployed controller runs, and the
  candidate's episode is simulated on the model from the same start with the same noise for
  the learner (:meth:`~mpcmobo.learners.Learner.observe_simulated`). The learner explores on
  the model what the plant would pay for, and the plant runs only candidates the model
  expects to pay for themselves; a simulated episode never deploys anything;
* after :data:`PATIENCE` candidates in a row that were refused or do not pay back (without a
  simulation), or :data:`SIMULATED_PATIENCE` in a row simulated (a learner that finds nothing
  worth the plant's episode), tuning has converged: every later episode runs the deployed
  controller without exploration noise, the learner no longer proposes nor observes, and the
  reason is kept (the tuner's ``status`` reports it). Where the model's ratio error alone
  exceeds the budget (``exp(s) >= 1 + budget``: the MPC's own wrong model, without
  identification, is off by a factor that depends on the start), the reason says that the
  model cannot price a candidate, and what to do: tune again with the model identified or with
  a larger budget (a run's budget is its settings'; a tuner takes another from its next trial
  on, :meth:`~mpcmobo.experiment.tuner.Tuner.load`); where the model is identified
  already, with a model whose equations hold the plant's physics, or with a larger budget.

A candidate whose predicted closed loop fails (the model's plant runs away) is refused; where
the deployed controller's prediction fails there is no basis, and the candidate runs.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

__all__ = [
    "PATIENCE",
    "SIMULATED_PATIENCE",
    "SIMULATION_ERROR",
    "UNPRICED",
    "ExplorationPrice",
    "Verdict",
]

# candidates in a row refused or not paying back after which tuning has converged
PATIENCE = 5
# candidates in a row simulated instead of run after which tuning has converged
SIMULATED_PATIENCE = 20
# the model's largest error (RMS log) at which a candidate's simulation stands in for its run
SIMULATION_ERROR = 0.05
# the model's calibration needs this many predicted episodes before it bounds a prediction
MIN_CALIBRATION = 2
# the last episodes kept to calibrate a new model on
RECENT = 6
# how the reason of a tuning that stopped exploring begins where the model cannot price a
# candidate (its error alone exceeds the budget)
UNPRICED = "the model cannot price a candidate"

# one past episode as the calibration keeps it: its start, theta, noise and plant cost
Episode = dict


@dataclass(frozen=True)
class Verdict:
    """Whether a candidate runs, whether it pays back its predicted excess, if either is not
    so, why (``reason``), and whether a refused candidate is simulated for the learner."""

    run: bool
    reason: str = ""
    pays: bool = True
    simulated: bool = False


class ExplorationPrice:
    """The gate of exploring episodes (module docstring). ``budget``: how much more than the
    deployed controller a candidate may be predicted to cost, as a fraction of the deployed
    controller's predicted cost (inf: no gate, nothing is predicted); ``episodes``: the run's
    budget of episodes (the remaining ones bound a payback); ``identifies``: whether the
    learner identifies the model (its predictions are then the identified model's, and a
    model that cannot price a candidate is not cured by identifying it)."""

    def __init__(self, budget: float, episodes: int, identifies: bool = False) -> None:
        if not budget >= 0:
            raise ValueError(f"the exploration budget must be >= 0 (inf: none), got {budget}")
        self.budget = float(budget)
        self.episodes = int(episodes)
        self.identifies = bool(identifies)
        self.errors_: list[float] = []  # log errors of the model's predictions
        self.model_ = ""  # the model they are of
        self.recent_: list[Episode] = []  # the last RECENT episodes, to calibrate a new model
        self.unpaid_ = 0  # candidates in a row refused or not paying back
        self.simulated_ = 0  # candidates in a row simulated instead of run
        self.converged_ = ""  # why tuning stopped exploring ("": it has not)
        self.converged_at_: int | None = None  # the episode of the last refusal before it

    @property
    def active(self) -> bool:
        """Whether the gate predicts and judges (a finite budget)."""
        return math.isfinite(self.budget)

    @property
    def converged(self) -> bool:
        """Whether tuning has stopped exploring."""
        return bool(self.converged_)

    def simulates(self) -> bool:
        """Whether the model is good enough for a refused candidate's simulation to be the
        learner's evidence: its error at most :data:`SIMULATION_ERROR`."""
        return self.error() <= SIMULATION_ERROR

    def error(self) -> float:
        """The model's error: the RMS log error of its predictions of the episodes run so far
        (inf before :data:`MIN_CALIBRATION` of them)."""
        if len(self.errors_) < MIN_CALIBRATION:
            return math.inf
        return float(np.sqrt(np.mean(np.square(self.errors_))))

    def ratio_error(self) -> float:
        """The model's error on the ratio of two of its predictions from one start: the
        standard deviation (one degree of freedom for the mean) of its log errors, inf before
        :data:`MIN_CALIBRATION` of them (module docstring)."""
        if len(self.errors_) < MIN_CALIBRATION:
            return math.inf
        return float(np.std(self.errors_, ddof=1))

    def use_model(self, key: str, predict: Callable[[list[Episode]], np.ndarray]) -> None:
        """Predict with the model ``key`` names from now on; a new one is calibrated on its
        predictions ``predict(episodes)`` of the last :data:`RECENT` episodes."""
        if key == self.model_:
            return
        self.model_, self.errors_ = key, []
        if self.recent_:
            predicted = predict(self.recent_)
            for p, ep in zip(predicted, self.recent_, strict=True):
                self._add_error(float(p), float(ep["cost"]))

    def calibrate(self, predicted: float, plant_cost: float, episode: Episode) -> None:
        """Take an episode's predicted and measured cost (an error where both are known and
        positive), and keep the ``episode`` (``x0``, ``theta``, ``noise``, ``cost``) for the
        next model's calibration."""
        self._add_error(predicted, plant_cost)
        if math.isfinite(plant_cost):
            self.recent_ = [*self.recent_, episode][-RECENT:]

    def _add_error(self, predicted: float, plant_cost: float) -> None:
        if math.isfinite(predicted) and math.isfinite(plant_cost):
            if predicted > 0 and plant_cost > 0:
                self.errors_.append(math.log(plant_cost / predicted))

    def judge(
        self,
        candidate: float,
        deployed: float,
        episode: int,
        gain: Callable[[], tuple[float, float]],
        learns: bool = False,
    ) -> Verdict:
        """Whether the candidate predicted to cost ``candidate`` runs where the deployed
        controller is predicted to cost ``deployed`` (both from the coming start of episode
        ``episode``, with its noise); ``gain()``: the candidate's predicted saving per episode
        were it deployed and the deployed controller's mean cost (module docstring; NaN where
        a closed loop fails), asked only when the candidate is costlier within the budget;
        ``learns``: whether the learner learns in simulation. A refusal, or a candidate that
        does not pay back, counts towards convergence; where the learner learns in simulation
        on a model good enough (:meth:`simulates`), neither runs: it is simulated."""
        verdict = self._verdict(candidate, deployed, self.episodes - int(episode) - 1, gain)
        if verdict.run and verdict.pays:
            self.unpaid_ = self.simulated_ = 0
            return verdict
        if learns and self.simulates():  # refused, or running without paying back
            self.simulated_ += 1
            if self.simulated_ >= SIMULATED_PATIENCE:
                self._converge(
                    f"{SIMULATED_PATIENCE} candidates in a row were learned from on the model only",
                    episode,
                    verdict,
                    "the learner finds nothing worth an episode on the plant",
                )
            return replace(verdict, run=False, simulated=True)
        self.unpaid_ += 1
        if self.unpaid_ >= PATIENCE:
            self._converge(
                f"{PATIENCE} candidates in a row were refused or could not pay back their "
                f"predicted excess",
                episode,
                verdict,
                self._why_unpaid(),
            )
        return verdict

    def _why_unpaid(self) -> str:
        """What :data:`PATIENCE` unpaid candidates in a row mean: exploring no longer pays, or,
        where the model's error alone exceeds the budget (a candidate predicted to cost what
        the deployed controller costs would be refused), that the model cannot price one."""
        spread = math.exp(self.ratio_error())
        if spread < 1 + self.budget:
            return "exploring no longer pays"
        within = (
            "it is not calibrated"
            if not math.isfinite(spread)
            else f"its cost ratios vary within a factor {spread:.3g}"
        )
        if self.identifies:  # the identified model's structure misses what the plant does
            cure = (
                "the model is identified already, and its structure misses what the plant "
                "does: tune again with a model whose equations hold the plant's physics, or "
                "with a larger budget"
            )
        else:
            cure = (
                "tune again with the model identified ([system] identify) or with a larger budget"
            )
        return (
            f"{UNPRICED} within the budget of {1 + self.budget:.3f}x "
            f"({within}): {cure} ([exploration] budget; inf runs every candidate)"
        )

    def _converge(self, streak: str, episode: int, verdict: Verdict, why: str) -> None:
        """Tuning has converged: ``streak`` says what came in a row, ``why`` what it means."""
        self.converged_ = f"{streak} (the last at episode {episode}: {verdict.reason}): {why}"
        self.converged_at_ = int(episode)

    def _verdict(
        self,
        candidate: float,
        deployed: float,
        remaining: int,
        gain: Callable[[], tuple[float, float]],
    ) -> Verdict:
        """The rule of the module docstring."""
        if not (math.isfinite(deployed) and deployed > 0):
            return Verdict(True)
        if not math.isfinite(candidate):
            return Verdict(False, "its closed loop on the model fails from this start")
        spread = math.exp(self.ratio_error())  # inf before the model is calibrated
        if candidate * spread > (1 + self.budget) * deployed:
            return Verdict(False, self._over_budget(candidate / deployed, spread))
        excess = candidate - deployed
        if excess <= 0:
            return Verdict(True)
        if remaining <= 0:
            return Verdict(True, "no episode is left to pay back its predicted excess", False)
        saving, mean = gain()
        if not math.isfinite(saving):
            return Verdict(False, "its closed loop on the model fails from a fixed start")
        if (saving + (spread - 1) * mean) * remaining < excess:
            return Verdict(
                True,
                f"its predicted excess of {100 * excess / deployed:.1f}% does not pay back in "
                f"{remaining} remaining episodes (predicted saving {saving:.4g} per episode, "
                f"{self._within()})",
                False,
            )
        return Verdict(True)

    def _over_budget(self, ratio: float, spread: float) -> str:
        """Why a candidate predicted at ``ratio`` times the deployed controller's cost is
        refused, with the model's error a factor ``spread`` (inf: not calibrated)."""
        budget = f"the budget of {1 + self.budget:.3f}x"
        if not math.isfinite(spread):
            return (
                f"predicted at {ratio:.3f}x the deployed controller's cost, but the model is "
                f"not calibrated yet (fewer than {MIN_CALIBRATION} of its predictions checked "
                f"against plant episodes): no prediction is trusted within {budget}"
            )
        return (
            f"predicted at {ratio:.3f}x the deployed controller's cost, up to "
            f"{ratio * spread:.3f}x with {self._within()}: over {budget}"
        )

    def _within(self) -> str:
        """How far the model's predictions are trusted, in words."""
        if not math.isfinite(self.error()):
            return "the model not calibrated yet"
        return f"the model's ratios within a factor {math.exp(self.ratio_error()):.3f}"

    def state_dict(self) -> dict:
        """What the gate has learned (its configuration comes from the settings)."""
        return {
            "errors": list(self.errors_),
            "model": self.model_,
            "recent": list(self.recent_),
            "unpaid": self.unpaid_,
            "simulated": self.simulated_,
            "converged": self.converged_,
            "converged_at": self.converged_at_,
            "episodes": self.episodes,
            "budget": self.budget,
        }

    def load_state_dict(self, state: dict | None) -> None:
        """Continue from a :meth:`state_dict` (None: a checkpoint without one). A run given
        more episodes than it had, or another budget, explores again: its remaining episodes,
        or what a candidate may cost, changed."""
        if state is None:
            return
        self.errors_ = [float(e) for e in state["errors"]]
        self.model_ = str(state["model"])
        self.recent_ = list(state["recent"])
        self.unpaid_ = int(state["unpaid"])
        self.simulated_ = int(state.get("simulated", 0))  # saved before simulated refusals
        # (a state saved before the budget was kept in it: the same budget)
        repriced = float(state.get("budget", self.budget)) != self.budget
        extended = int(state["episodes"]) != self.episodes or repriced
        self.converged_ = "" if extended else str(state["converged"])
        at = None if extended else state.get("converged_at")  # saved before it was kept
        self.converged_at_ = None if at is None else int(at)
        if extended:
            self.unpaid_ = self.simulated_ = 0
