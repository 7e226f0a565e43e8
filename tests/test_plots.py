"""Figures 1-4 from the records of a small real run (two seeds: median and IQR bands)."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from matplotlib.colors import to_rgb
from matplotlib.image import imread
from typer.testing import CliRunner

from mpcmobo.cli import app
from mpcmobo.experiment.settings import load_settings
from mpcmobo.experiment.study import run_study
from mpcmobo.plots import FIGURES, fig1, fig2, pareto_mask


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("plots") / "run"
    s = load_settings(
        None,
        system={"name": "cstr"},
        learners=["mpc-rl"],
        episodes=4,
        steps=8,
        seeds=[0, 1],
        evaluation={"n_starts": 2, "eval_every": 2},
        records={"trajectory_every": 2},
        workers=1,
    )
    run_study(s, out)
    return out


def test_plot_writes_all_four_figures(small_run):
    res = CliRunner().invoke(app, ["plot", str(small_run)])
    assert res.exit_code == 0, res.output
    for name in FIGURES:
        for ext in ("png", "pdf"):
            p = small_run / "figures" / f"{name}.{ext}"
            assert p.exists() and p.stat().st_size > 1000, p
    assert (small_run / "figures" / "fig1_performance.png").read_bytes()[:4] == b"\x89PNG"
    assert (small_run / "figures" / "fig3_states.pdf").read_bytes()[:4] == b"%PDF"
    # each PNG is a drawn figure, not a blank canvas: many colours, and the learner's colour
    # (MPC-RL: tab:green) in the curves of figures 1-4 (fig. 3 and 4: the imperfect MPC)
    green = np.array(to_rgb("tab:green"))
    for name in FIGURES:
        img = imread(small_run / "figures" / f"{name}.png")[..., :3]
        assert img.shape[0] > 300 and img.shape[1] > 500, name
        assert len(np.unique(img.reshape(-1, 3).round(2), axis=0)) > 20, name
        assert np.any(np.all(np.abs(img - green) < 0.02, axis=-1)), name


def test_figures_draw_the_records(small_run):
    """Figure 1 plots the records: per episode the median over seeds of J tilde and of the
    evaluated incumbent's J_eval, and J* of the summary; the figure-2 advantage panel the
    median of mean |A^w|."""
    ep = pd.read_parquet(small_run / "episodes.parquet")
    summary = json.loads((small_run / "summary.json").read_text())
    assert ep.seed.nunique() == 2
    ax = fig1(ep, summary, ["mpc-rl"]).axes[0]
    lines = {line.get_label(): line for line in ax.get_lines()}
    J = ep.groupby("episode")["J_tilde"].median()
    curve = lines[r"$\tilde J$ MPC-RL"]
    np.testing.assert_array_equal(curve.get_xdata(), J.index)
    np.testing.assert_allclose(curve.get_ydata(), J.to_numpy())
    ev = ep[np.isfinite(ep.J_eval_incumbent)].groupby("episode")["J_eval_incumbent"].median()
    curve = lines[r"$J_{eval}$ incumbent"]
    np.testing.assert_array_equal(curve.get_xdata(), ev.index)
    np.testing.assert_allclose(curve.get_ydata(), ev.to_numpy())
    np.testing.assert_allclose(lines[r"$J^\star$"].get_ydata(), summary["J_star"])
    adv = fig2(ep, ["mpc-rl"]).axes[0].get_lines()[0]
    np.testing.assert_allclose(adv.get_ydata(), ep.groupby("episode")["mean_abs_A"].median())


def test_plot_errors(small_run, tmp_path):
    res = CliRunner().invoke(app, ["plot", str(tmp_path)])
    assert res.exit_code == 2 and "config.toml" in res.output
    res = CliRunner().invoke(app, ["plot", str(small_run), "--learner", "bo"])
    assert res.exit_code == 2 and "not in this run" in res.output


def test_pareto_mask():
    Y = np.array([[1.0, 2.0], [2.0, 1.0], [2.0, 2.0], [0.5, 3.0], [np.nan, 0.0], [1.0, 2.0]])
    assert pareto_mask(Y).tolist() == [True, True, False, True, False, True]
