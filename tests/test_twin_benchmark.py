"""benchmarks/twin.py: the twin's tuning from theta0 on the true model, scored on its own
starts, fresh starts and the evaluation starts."""

from __future__ import annotations

import numpy as np


def test_the_twins_theta_is_never_worse_on_the_starts_it_was_tuned_on(tmp_path, benchmark_script):
    """theta0 is the tuning's first evaluation and the cheapest theta is its result, so on its
    own starts the ratio to J* is at most 1, and below 1 exactly when the twin found better;
    the other sets are scored too, and the table reports them."""
    tb = benchmark_script("twin")
    config = tmp_path / "lq.toml"
    config.write_text('[system]\nname = "lq"\nidentify = true\n')
    rows = [tb._job(str(config), 2, seed, 3, 4) for seed in (0, 1)]
    for r in rows:
        assert r["tuned_on"] <= 1.0 + 1e-12
        assert r["better"] == (r["tuned_on"] < 1.0)
        assert np.isfinite(r["fresh"]) and np.isfinite(r["eval"]) and r["seconds"] > 0
    table = tb._table(rows)
    assert table.splitlines()[2].startswith("| 2 | 2 |")


def test_from_a_run_it_tunes_identifys_theta_on_the_plant(tmp_path, benchmark_script):
    """With a run, the tuning starts from the run's final `identify` theta of the seed and runs
    on the plant itself: given the true model's theta0 there (what `identify` reaches on `lq`),
    every ratio is the default tuning's; a run without that seed's `identify` is an error
    that names it."""
    import pandas as pd
    import pytest

    from mpcmobo.experiment.build import build_system, identified_parameters
    from mpcmobo.experiment.settings import load_settings
    from mpcmobo.identify import ModelFit
    from mpcmobo.mpc import ParametricMPC

    tb = benchmark_script("twin")
    run = tmp_path / "run"
    run.mkdir()
    config = run / "config.toml"
    config.write_text('[system]\nname = "lq"\nidentify = true\n')
    settings = load_settings(config)
    system = build_system(settings, "identify")
    fit = ModelFit(system, identified_parameters(settings, system, "identify"))
    mpc = ParametricMPC(system, model="imperfect", **settings.mpc.options())
    theta = fit.theta_with(mpc.theta0, np.asarray(system.true_params, float)[fit.index])
    space = system.search_space
    stale = np.full_like(theta, np.nan)  # an earlier episode's theta: the last one counts
    pd.DataFrame(
        {
            "learner": ["identify", "identify", "bo", "identify"],
            "seed": [0, 0, 1, 2],
            "episode": [1, 0, 0, 0],
            "incumbent": [list(theta), list(stale), list(theta), list(space.clip(1.5 * theta))],
            "J_eval_incumbent": [1.0, 2.0, 1.0, 1.0],
        }
    ).to_parquet(run / "episodes.parquet")
    ours = tb._job(str(config), 2, 0, 3, 4, str(run))
    default = tb._job(str(config), 2, 0, 3, 4)
    for key in ("tuned_on", "fresh", "eval", "cycle", "better"):
        assert ours[key] == default[key]
    other = tb._job(str(config), 2, 2, 3, 4, str(run))  # another theta: other ratios
    assert other["fresh"] != tb._job(str(config), 2, 2, 3, 4)["fresh"]
    with pytest.raises(SystemExit, match="'identify' with seed 1"):
        tb._job(str(config), 2, 1, 3, 4, str(run))
    assert "seeds above `identify`" in tb._table([ours], "`identify`")
