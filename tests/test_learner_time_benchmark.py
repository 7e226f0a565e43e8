"""benchmarks/learner_time.py: a finished job's learner replayed from its checkpoint."""

from __future__ import annotations

import argparse
import pickle

import numpy as np
import pytest
from typer.testing import CliRunner

from mpcmobo.cli import app


@pytest.fixture(scope="module")
def mobo_run(tmp_path_factory):
    """A finished mobo job on lq without identification nor budget, 4 episodes of 8 steps."""
    out = tmp_path_factory.mktemp("learner_time")
    config = out / "lq.toml"
    config.write_text('[system]\nname = "lq"\nidentify = false\n[exploration]\nbudget = inf\n')
    args = ["run", "-c", str(config), "-l", "mobo", "-n", "4", "--steps", "8", "--seeds", "0"]
    res = CliRunner().invoke(app, [*args, "-q", "--no-plot", "--out", str(out / "run")])
    assert res.exit_code == 0, res.output
    return out / "run"


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
