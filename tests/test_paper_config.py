"""benchmarks/configs/paper.toml, the paper's protocol (issue 15): it loads, its learners accept
their options, and it says what section 5 of the paper says."""

from __future__ import annotations

import tomllib
from pathlib import Path

from mpcmobo.experiment.settings import load_settings, validate_settings
from mpcmobo.experiment.study import check_learners

PAPER = Path(__file__).parents[1] / "benchmarks" / "configs" / "paper.toml"
# the paper's constant step rule in theta itself (eq. theta) with its step size, and the iterate
# deployed (no judge)
PAPER_RL = {"optimizer": "gd", "lr": 0.003, "deploy": "iterate"}


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
    """Every learner accepts its options, and MPC-RL steps and deploys as the paper does."""
    data = tomllib.loads(PAPER.read_text())
    options = data["learner_options"]["mpc-rl"]
    assert {k: options[k] for k in PAPER_RL} == PAPER_RL
    check_learners(validate_settings(data))
    assert data["learner_options"]["bo"]["context"] == "none"
    assert data["learner_options"]["mobo"]["context"] == "none"


def test_every_benchmark_config_loads_and_its_learners_accept_their_options():
    """Each file of benchmarks/configs (the options that docs/benchmarks.md measures) is valid
    settings, and every learner it configures accepts its options: a misspelt option in one of
    them is an error here, not a silently different benchmark."""
    files = sorted(PAPER.parent.glob("*.toml"))
    assert PAPER in files and len(files) > 5
    for path in files:
        data = tomllib.loads(path.read_text())
        settings = validate_settings(data)
        check_learners(
            settings.model_copy(update={"learners": list(data.get("learner_options", {}))})
        )
