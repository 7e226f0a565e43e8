"""benchmarks/configs/paper.toml, the paper's protocol: it loads, its learners accept their
options, MPC-RL steps and deploys as the paper does (the plain step in theta, the iterate
deployed) and BO and MOBO deploy the GP's incumbent over the whole box (no trust region)."""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest

from mpcmobo.experiment.build import build_system
from mpcmobo.experiment.job import make_study_learner
from mpcmobo.experiment.settings import load_settings
from mpcmobo.experiment.study import check_learners
from mpcmobo.learners.base import EpisodeResult
from mpcmobo.learners.deploy import Incumbent
from mpcmobo.learners.options import IncumbentDeploy, IterateDeploy, PlainStep
from mpcmobo.rl.steps import PlainGradient

CONFIGS = Path(__file__).parents[1] / "benchmarks" / "configs"
PAPER = CONFIGS / "paper.toml"


@pytest.fixture(scope="module")
def paper():
    settings = load_settings(PAPER)
    return settings, build_system(settings)


def test_every_benchmark_config_loads_and_the_benchmark_page_names_only_those():
    """Each config of benchmarks/configs loads and resolves; every config a command of
    docs/benchmarks.md names is one of them."""
    import re

    names = sorted(p.name for p in CONFIGS.glob("*.toml"))
    for name in names:
        load_settings(CONFIGS / name).resolved()
    page = (CONFIGS.parents[1] / "docs" / "benchmarks.md").read_text()
    named = set(re.findall(r"--config (\S+\.toml)", page)) - {"examples/cartpole.toml"}
    assert named and all(n.startswith("benchmarks/configs/") for n in named), named
    assert {n.removeprefix("benchmarks/configs/") for n in named} <= set(names)


def test_the_configs_without_identification_explore_without_a_price():
    """Without identification the only model is the MPC's own wrong one, which cannot price a
    candidate: every benchmark config that turns identification off runs every candidate."""
    off = [p for p in sorted(CONFIGS.glob("*.toml")) if load_settings(p).system.identify is False]
    assert {p.name for p in off} >= {"default_noident.toml", "noident.toml", "paper.toml"}
    for p in off:
        assert load_settings(p).resolved().exploration.budget == float("inf"), p.name


def test_paper_config_loads_with_the_papers_protocol(paper):
    s = paper[0].resolved()
    assert (s.episodes, s.steps, s.start_mode, s.mpc.horizon) == (600, 60, "random", 10)
    assert (s.critic.method, s.critic.q_target, s.critic.weighting) == (
        "paper",
        "V_theta",
        "uniform",
    )
    assert s.learners == ["mpc-rl", "bo", "mobo"] and s.system.name == "cstr"
    assert s.exploration.std == [1.7, 1.7] and not s.system.learn_model
    assert s.system.identify is False  # the paper tunes the imperfect model; the default fits it
    assert s.exploration.budget == float("inf")  # every candidate runs: no exploration budget


def test_paper_config_learner_options_are_the_papers_rules(paper):
    """The file's tables, read as the learners read them: the gd rule with alpha = 0.003 and
    the iterate deployed; BO and MOBO with the incumbent rule and no trust region. Every
    learner accepts its options."""
    settings, _ = paper
    data = tomllib.loads(PAPER.read_text())
    assert data["learner_options"]["mpc-rl"] == {
        "optimizer": {"rule": "gd", "lr": 0.003},
        "deploy": "iterate",
    }
    for name in ("bo", "mobo"):
        assert data["learner_options"][name] == {"trust_region": False, "deploy": "incumbent"}
    check_learners(settings)
    resolved = settings.resolved().learner_options
    assert resolved["mpc-rl"]["optimizer"] == {"rule": "gd", "lr": 0.003}
    assert resolved["mpc-rl"]["deploy"] == {"rule": "iterate"}
    for name in ("bo", "mobo"):
        assert resolved[name]["deploy"] == {"rule": "incumbent"}
        assert resolved[name]["trust_region"] is False


def _result(grad: np.ndarray, f1: float = 1.0) -> EpisodeResult:
    return EpisodeResult(objectives=np.array([f1, 1.0, 0.0, 0.0]), grad=grad, critic_ok=True)


def test_paper_mpc_rl_steps_in_theta_and_deploys_the_iterate(paper):
    """Built from the file for the study's random starts, MPC-RL takes the plain step
    ``theta - 0.003 grad`` in theta itself on its first episode, explores on every episode (no
    verification block) and deploys the new iterate at once."""
    settings, system = paper
    theta0 = system.parameterization.theta0
    learner = make_study_learner(settings, system, "mpc-rl", theta0, seed=0)
    assert isinstance(learner.options.optimizer, PlainStep)
    assert isinstance(learner.options.deploy, IterateDeploy)
    assert isinstance(learner.rule, PlainGradient) and learner.rule.lr == 0.003
    assert learner.blocks_ is None and learner.explores()
    theta = learner.propose()
    np.testing.assert_array_equal(theta, learner.incumbent())
    space = system.search_space
    grad = np.zeros(len(theta0))
    i = int(np.flatnonzero(space.free)[0])  # a searched coordinate, moved well inside its bounds
    grad[i] = -0.01 * abs(theta[i]) / 0.003 - 1.0
    learner.observe(theta, _result(grad))
    expected = space.clip(theta - 0.003 * grad)
    np.testing.assert_allclose(learner.incumbent(), expected, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(learner.propose(), expected, rtol=1e-10, atol=1e-12)
    assert not np.array_equal(learner.incumbent(), theta)


@pytest.mark.parametrize("name", ["bo", "mobo"])
def test_paper_gp_learners_use_the_incumbent_rule_without_trust_region(paper, name):
    settings, system = paper
    theta0 = system.parameterization.theta0
    learner = make_study_learner(settings, system, name, theta0, seed=0)
    assert isinstance(learner.options.deploy, IncumbentDeploy)
    assert isinstance(learner.policy, Incumbent)
    assert learner.options.trust_region is False and learner.trust_region is None
    assert learner.trust_ is None and learner._trust_box() is None
    # the initial design spreads over the whole cube, not a box around theta0
    z0 = system.search_space.to_unit(theta0)
    design = learner.design[1:]
    assert np.max(np.abs(design - z0)) > 0.2
