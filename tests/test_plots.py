"""Figures 1-4 from the records of a small real run (two seeds: median and IQR bands)."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from mpcmobo.cli import app
from mpcmobo.experiment.settings import load_settings
from mpcmobo.experiment.study import run_study
from mpcmobo.plots import FIGURES, pareto_mask


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


def test_plot_errors(small_run, tmp_path):
    res = CliRunner().invoke(app, ["plot", str(tmp_path)])
    assert res.exit_code == 2 and "config.toml" in res.output
    res = CliRunner().invoke(app, ["plot", str(small_run), "--learner", "bo"])
    assert res.exit_code == 2 and "not in this run" in res.output


def test_pareto_mask():
    Y = np.array([[1.0, 2.0], [2.0, 1.0], [2.0, 2.0], [0.5, 3.0], [np.nan, 0.0], [1.0, 2.0]])
    assert pareto_mask(Y).tolist() == [True, True, False, True, False, True]
