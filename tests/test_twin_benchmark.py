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
