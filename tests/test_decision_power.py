"""benchmarks/decision_power.py's learned start model (issue 11, session 15): it finds a hot
region of the starts from episodes of several thetas, predicts each episode without its own
cost, and falls back to no start effect where the starts explain nothing."""

import importlib.util
from pathlib import Path

import numpy as np

SCRIPT = Path(__file__).parents[1] / "benchmarks" / "decision_power.py"
spec = importlib.util.spec_from_file_location("decision_power", SCRIPT)
assert spec is not None and spec.loader is not None
decision_power = importlib.util.module_from_spec(spec)
spec.loader.exec_module(decision_power)


def _episodes(rng, hot_factor):
    x = rng.uniform(size=(60, 2))
    group = rng.integers(4, size=60)
    offset = np.array([0.0, -0.1, 0.2, 0.05])[group]  # per-theta effects
    hot = x[:, 0] < 0.3
    y = offset + np.log(hot_factor) * hot + 0.05 * rng.standard_normal(60)
    return x, y, group, hot


def test_start_effect_finds_the_hot_region():
    x, y, group, hot = _episodes(np.random.default_rng(0), hot_factor=8.0)
    f = decision_power.start_effect(x, y, group, n_test=20)
    ratio = np.median(f[:20][hot[:20]]) / np.median(f[:20][~hot[:20]])
    assert 4.0 < ratio < 16.0  # about the factor 8, each episode predicted without itself


def test_start_effect_is_one_without_a_start_effect():
    x, y, group, _ = _episodes(np.random.default_rng(1), hot_factor=1.0)
    f = decision_power.start_effect(x, y, group, n_test=20)
    assert np.all(np.abs(np.log(f)) < 0.1)


def test_start_effect_leaves_the_episode_out():
    """An episode's own cost does not make its start look hot: a cold start whose episode cost
    as much as a hot one is predicted like the other cold starts."""
    x, y, group, hot = _episodes(np.random.default_rng(2), hot_factor=8.0)
    i = int(np.flatnonzero(~hot)[0])
    y = y.copy()
    y[i] += np.log(8.0)
    g = np.log(decision_power.start_effect(x, y, group, n_test=len(y)))
    others = np.median(np.delete(g, i)[~np.delete(hot, i)])
    assert abs(g[i] - others) < 0.2
