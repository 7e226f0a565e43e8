"""benchmarks/learner_time.py: a finished job's learner replayed from its checkpoint."""

from __future__ import annotations

import argparse
import pickle

import numpy as np
import pytest
from typer.testing import CliRunner

from mpcmobo.cli import app


def _mobo_run(out, budget: str):
    """A finished mobo job on lq without identification, 4 episodes of 8 steps."""
    config = out / "lq.toml"
    config.write_text(
        f'[system]\nname = "lq"\nidentify = false\n[exploration]\nbudget = {budget}\n'
    )
    args = ["run", "-c", str(config), "-l", "mobo", "-n", "4", "--steps", "8", "--seeds", "0"]
    res = CliRunner().invoke(app, [*args, "-q", "--no-plot", "--out", str(out / "run")])
    assert res.exit_code == 0, res.output
    return out / "run"


@pytest.fixture(scope="module")
def mobo_run(tmp_path_factory):
    """Without an exploration budget: the learner's evidence is the run's episodes."""
    return _mobo_run(tmp_path_factory.mktemp("learner_time"), "inf")


def test_the_states_are_the_checkpoint_cut_to_each_sampled_episode(mobo_run, benchmark_script):
    """Each sampled state is the final checkpoint's learner with its evidence cut to the first
    ``i`` episodes; it loads into the run's learner, which then proposes a theta and observes
    the recorded episode (what the benchmark times)."""
    lt = benchmark_script("learner_time")
    args = argparse.Namespace(run=mobo_run, learner="mobo", seed=0, offset=1, stride=2, first=1)
    data = lt.record(args)
    assert data["n"] == 4 and sorted(data["states"]) == [1, 3]
    rows = lt._rows(mobo_run, "mobo", 0)
    for i, blob in data["states"].items():
        state = pickle.loads(blob)
        per_episode = [v for v in state["evidence"].values() if isinstance(v, list | np.ndarray)]
        assert per_episode and all(len(v) == i for v in per_episode)
        learner, settings = lt._learner(mobo_run, "mobo", 0)
        learner.load_state_dict(state)
        theta = np.asarray(rows[i]["theta"], float)
        proposal = learner.propose()
        assert proposal.shape == theta.shape and np.all(np.isfinite(proposal))
        result = lt._result(rows[i], settings.n_cycle_starts, settings.start_mode, len(theta))
        learner.observe(theta, result)
        assert learner.n_observed == len(learner.evidence_) == i + 1


def test_a_job_that_identifies_its_model_is_named(dashboard_run, benchmark_script):
    lt = benchmark_script("learner_time")
    args = argparse.Namespace(
        run=dashboard_run, learner="mobo", seed=0, offset=1, stride=1, first=1
    )
    with pytest.raises(SystemExit, match="mobo-s0 identifies its model first"):
        lt.record(args)


def test_a_job_that_learned_from_simulated_candidates_is_named(tmp_path, benchmark_script):
    """With the default budget the learner also learns from refused candidates simulated on
    the model: its evidence is not the run's episodes, and the replay says so."""
    lt = benchmark_script("learner_time")
    run = _mobo_run(tmp_path, "0.5")
    args = argparse.Namespace(run=run, learner="mobo", seed=0, offset=1, stride=1, first=1)
    with pytest.raises(SystemExit, match="4 ran on the plant .* budget = inf"):
        lt.record(args)
