"""benchmarks/twin.py: the twin's tuning from theta0 on the true model, scored on its own
starts, fresh starts and the evaluation starts."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import numpy as np


def _twin_benchmark():  # noqa: ANN202 - the script as a module
    path = Path(__file__).parents[1] / "benchmarks" / "twin.py"
    spec = importlib.util.spec_from_file_location("twin_benchmark", path)
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_the_twins_theta_is_never_worse_on_the_starts_it_was_tuned_on(tmp_path):
    """theta0 is the tuning's first evaluation and the cheapest theta is its result, so on its
    own starts the ratio to J* is at most 1, and below 1 exactly when the twin found better;
    the other sets are scored too, and the table reports them."""
    tb = _twin_benchmark()
    config = tmp_path / "lq.toml"
    config.write_text('[system]\nname = "lq"\nidentify = true\n')
    rows = [tb._job(str(config), 2, seed, 3, 4) for seed in (0, 1)]
    for r in rows:
        assert r["tuned_on"] <= 1.0 + 1e-12
        assert r["better"] == (r["tuned_on"] < 1.0)
        assert np.isfinite(r["fresh"]) and np.isfinite(r["eval"]) and r["seconds"] > 0
    table = tb._table(rows)
    assert table.splitlines()[2].startswith("| 2 | 2 |")
