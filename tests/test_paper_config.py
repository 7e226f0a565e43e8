"""benchmarks/configs/paper.toml, the paper's protocol (issue 15): it loads, its learners accept
their options, and it says what section 5 of the paper says."""

from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from mpcmobo.experiment.settings import load_settings, validate_settings
from mpcmobo.experiment.study import check_learners
from mpcmobo.learners.registry import learner_options

PAPER = Path(__file__).parents[1] / "benchmarks" / "configs" / "paper.toml"


def test_paper_config_loads_with_the_papers_protocol():
    s = load_settings(PAPER).resolved()
    assert (s.episodes, s.steps, s.start_mode, s.mpc.horizon) == (600, 60, "random", 10)
    assert (s.critic.method, s.critic.q_target, s.critic.weighting) == (
        "paper",
        "V_theta",
        "uniform",
    )
    assert s.learners == ["mpc-rl", "bo", "mobo"] and s.system.name == "cstr"
    assert s.exploration.std == [1.7, 1.7] and not s.system.learn_model


def test_paper_config_learner_options():
    """Every learner accepts its options. The constant step rule of MPC-RL (step_rule, branch
    i11-rl) is checked once the learner has it; until then only that line is left out."""
    data = tomllib.loads(PAPER.read_text())
    assert data["learner_options"]["mpc-rl"]["step_rule"] == "sgd"
    if "step_rule" not in learner_options("mpc-rl"):
        del data["learner_options"]["mpc-rl"]["step_rule"]
        with pytest.raises(Exception, match="step_rule"):
            check_learners(load_settings(PAPER))
    check_learners(validate_settings(data))
