"""Optuna as a peer learner for the learning benchmark: what a user would pick instead of
mpcmobo.

``optuna-tpe`` and ``optuna-gp`` tune the same theta as the other learners, in the same unit
cube of the search space (one ``suggest_float(f"z{i}", 0, 1)`` per free coordinate), through the
same episode loop, seeds and starts. The first trial is theta0 (``enqueue_trial``); each episode
is one trial whose value is its closed-loop cost f1 (a failed episode is a failed trial); the
deployed theta (the incumbent, what J_eval measures) is the best trial's (theta0 itself while
that is the enqueued first trial). The samplers run at Optuna's defaults, seeded with the
learner's seed, as a new user would run them.

Optuna is an optional benchmark dependency (``pip install -e ".[bench]"``), never imported by
the package: ``register()`` adds the two learners to the registry of this process only, so the
benchmark runs them with ``workers = 1`` (spawned workers would not know them).
"""

from __future__ import annotations

import pickle

import numpy as np

from mpcmobo.learners.base import EpisodeResult, Learner, Starts
from mpcmobo.learners.registry import LearnerSpec, register_learner
from mpcmobo.systems.space import SearchSpace

SAMPLERS = ("tpe", "gp")


class OptunaLearner(Learner):
    """One Optuna study behind the propose / observe interface (see the module docstring)."""

    sampler_name = "tpe"

    def __init__(
        self, space: SearchSpace, theta0: np.ndarray, seed: int = 0, *, starts: Starts | None = None
    ) -> None:
        super().__init__(space, theta0, seed, starts=starts)
        self.study = self._new_study()
        self.z0 = space.to_unit(self.theta0)
        self.study.enqueue_trial(self._params(self.z0))
        self._trial = None  # the trial asked for and not told yet

    def _new_study(self):
        import optuna

        optuna.logging.set_verbosity(optuna.logging.WARNING)
        if self.sampler_name == "tpe":
            sampler = optuna.samplers.TPESampler(seed=self.seed)
        else:
            sampler = optuna.samplers.GPSampler(seed=self.seed)
        return optuna.create_study(direction="minimize", sampler=sampler)

    def _params(self, z: np.ndarray) -> dict[str, float]:
        return {f"z{i}": float(v) for i, v in enumerate(z)}

    def _z(self, params: dict[str, float]) -> np.ndarray:
        return np.array([params[f"z{i}"] for i in range(self.space.dim)], dtype=float)

    def propose(self) -> np.ndarray:
        if self._trial is None:
            self._trial = self.study.ask()
            for i in range(self.space.dim):
                self._trial.suggest_float(f"z{i}", 0.0, 1.0)
        return self.theta_of(self._z(self._trial.params))

    def observe(self, theta: np.ndarray, result: EpisodeResult) -> None:
        from optuna.trial import TrialState

        self.n_observed += 1
        if self._trial is None:  # an episode that did not run our proposal: nothing to tell
            return
        if np.isfinite(result.f1):
            self.study.tell(self._trial, float(result.f1))
        else:
            self.study.tell(self._trial, state=TrialState.FAIL)
        self._trial = None

    def incumbent(self) -> np.ndarray:
        from optuna.trial import TrialState

        if not self.study.get_trials(deepcopy=False, states=(TrialState.COMPLETE,)):
            return self.theta0.copy()
        return self.theta_of(self._z(self.study.best_trial.params))

    def state_dict(self) -> dict:
        d = super().state_dict()
        d["optuna_study"] = pickle.dumps((self.study, self._trial))
        return d

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        self.study, self._trial = pickle.loads(state["optuna_study"])


class OptunaTPE(OptunaLearner):
    name = "optuna-tpe"
    sampler_name = "tpe"


class OptunaGP(OptunaLearner):
    name = "optuna-gp"
    sampler_name = "gp"


def register() -> None:
    """Make ``optuna-tpe`` and ``optuna-gp`` known to this process's study runner."""
    register_learner(
        LearnerSpec("optuna-tpe", OptunaTPE, "Optuna TPE", "tab:brown", job_cost=2, in_paper=False)
    )
    register_learner(
        LearnerSpec("optuna-gp", OptunaGP, "Optuna GP", "tab:olive", job_cost=2, in_paper=False)
    )
