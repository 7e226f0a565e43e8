"""Fault injection: failed MPC solves at random steps, NaN and inf objectives, and a
learner whose proposal raises; each is recorded and the run goes on, with no crash."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mpcmobo.experiment import loop, storage
from mpcmobo.experiment.settings import load_settings
from mpcmobo.experiment.study import run_study
from mpcmobo.learners.gp import BOLearner
from mpcmobo.learners.identified import IdentifyFirst
from mpcmobo.learners.mpc_rl import MPCRL
from mpcmobo.mpc import ParametricMPC

EPISODES = 8
FAST_SEARCH = {"num_restarts": 2, "raw_samples": 32, "maxiter": 20}  # a cheap acquisition search


def small(learners, identify=False, **kw):
    """A short study on ``lq``: the learners tune the nominal model unless ``identify``."""
    return load_settings(
        None,
        system={"name": "lq", "identify": identify},
        learners=learners,
        episodes=EPISODES,
        steps=8,
        workers=1,
        evaluation={"n_starts": 2},
        learner_options={"bo": {"n_init": 3, "search": FAST_SEARCH}},
        **kw,
    )


def test_failed_solves_at_random_steps_use_the_fallback_and_are_recorded(tmp_path, monkeypatch):
    rng = np.random.default_rng(14)
    injected = []
    original = ParametricMPC.solve

    def flaky(self, x, theta=None, sensitivities=True):
        if sensitivities and rng.random() < 0.15:  # a learning episode's solve
            injected.append(1)
            return self._failed_solution("Injected_Failure", 0, sensitivities)
        return original(self, x, theta, sensitivities)

    monkeypatch.setattr(ParametricMPC, "solve", flaky)
    summary = run_study(small(["mpc-rl", "bo"]), tmp_path / "run")
    assert summary["complete"] is True
    df = storage.read_episodes(tmp_path / "run")
    assert len(df) == 2 * EPISODES and (df.error == "").all()
    assert df.solver_failures.sum() == len(injected) > 0
    hit = df[df.solver_failures > 0]
    assert len(hit) > 0 and np.isfinite(hit.f1).all()  # the episode went on with the fallback


@pytest.mark.parametrize("learner", ["mpc-rl", "bo"])
def test_nan_and_inf_objectives_are_recorded_not_fitted(tmp_path, monkeypatch, learner):
    bad = {2: (0, math.nan), 3: (0, math.inf), 5: (1, -math.inf), 6: (3, math.nan)}
    original = loop.episode_result
    calls = []

    def corrupt(record, critic, previous_Vc, beta=1.0, **kw):
        result, cr = original(record, critic, previous_Vc, beta, **kw)
        k = len(calls)
        calls.append(k)
        if k in bad:
            i, value = bad[k]
            result.objectives = result.objectives.copy()
            result.objectives[i] = value
        return result, cr

    monkeypatch.setattr(loop, "episode_result", corrupt)
    summary = run_study(small([learner]), tmp_path / "run")
    assert summary["complete"] is True
    df = storage.read_episodes(tmp_path / "run")
    assert len(df) == EPISODES and (df.error == "").all()
    for k, (i, value) in bad.items():
        got = df.loc[k, f"f{i + 1}"]
        assert (math.isnan(got) and math.isnan(value)) or got == value
    incumbents = np.array(df.incumbent.tolist())
    assert np.isfinite(incumbents).all()
    if learner == "bo":  # an episode with a non-finite objective is never the incumbent
        thetas = np.array(df.theta.tolist())
        first = [
            next(j for j in range(len(thetas)) if np.array_equal(thetas[j], t)) for t in thetas
        ]
        for j in range(EPISODES):
            for k in bad:
                if first[k] == k and k <= j:
                    assert not np.array_equal(incumbents[j], thetas[k])


@pytest.mark.parametrize(
    "learner, cls, identify",
    [("mpc-rl", MPCRL, False), ("bo", BOLearner, False), ("bo", IdentifyFirst, True)],
)
def test_a_failing_proposal_is_recorded_and_the_incumbent_runs(
    tmp_path, monkeypatch, learner, cls, identify
):
    original = cls.propose
    calls = []

    def failing(self):
        calls.append(1)
        if len(calls) in (3, 6):
            raise RuntimeError("injected failure in the proposal")
        return original(self)

    monkeypatch.setattr(cls, "propose", failing)
    summary = run_study(small([learner], identify), tmp_path / "run")
    assert summary["complete"] is True
    df = storage.read_episodes(tmp_path / "run")
    assert len(df) == EPISODES
    for k in (2, 5):
        assert "proposal failed" in df.error[k] and "injected failure" in df.error[k]
        assert np.array_equal(df.theta[k], df.incumbent[k - 1])  # the incumbent ran
        assert np.isfinite(df.f1[k])
    assert (df.error.drop([2, 5]) == "").all()
