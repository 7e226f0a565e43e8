"""Runs written by mpcmobo 0.1.0: refused on resume, their records still readable.

``tests/data/checkpoints_v0.1`` holds an LQ study (mpc-rl and mobo, 8 episodes) that 0.1.0
interrupted after 4 episodes (``run/``: its settings, reference and job checkpoints of
checkpoint schema 1), and the records of the same study run uninterrupted by that version
(``expected_*.parquet``); ``make_fixture.py`` made both with that version. 1.0's learners keep
another state (options objects and evidence), so such a run cannot continue: ``--resume``
exits with code 2 naming the version and what to do, and writes nothing. What the run
recorded stays readable: ``mpcmobo plot`` draws its records and ``mpcmobo evaluate`` evaluates
the incumbents of its checkpoints.
"""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import mpcmobo
from mpcmobo.cli import app
from mpcmobo.experiment import storage
from mpcmobo.experiment.rundir import OlderRunError, RunDirectory
from mpcmobo.experiment.settings import load_settings
from mpcmobo.experiment.study import run_study
from mpcmobo.plots import FIGURES

DATA = Path(__file__).parent / "data" / "checkpoints_v0.1"
JOBS = {"mpc-rl": 0, "mobo": 0}  # the fixture's jobs (learner: seed)
RESUMED_AT = 4  # the checkpoints hold episodes 0-3 of each job
runner = CliRunner()


@pytest.fixture
def old_run(tmp_path) -> Path:
    """A copy of the interrupted 0.1.0 run."""
    out = tmp_path / "run"
    shutil.copytree(DATA / "run", out)
    return out


@pytest.fixture
def old_records(old_run) -> Path:
    """The copy with that version's records beside its checkpoints, as 0.1.0 wrote them."""
    shutil.copy(DATA / "expected_episodes.parquet", old_run / "episodes.parquet")
    shutil.copy(DATA / "expected_trajectories.parquet", old_run / "trajectories.parquet")
    return old_run


def snapshot(directory: Path) -> dict[str, tuple[str, int]]:
    """Every file and directory under ``directory``: content hash (directories: "") and
    modification time."""
    out = {}
    for p in sorted(directory.rglob("*")):
        digest = hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else ""
        out[str(p.relative_to(directory))] = (digest, p.stat().st_mtime_ns)
    return out


def test_the_fixture_is_a_schema_1_run():
    """What the tests below rely on: both checkpoints are 0.1.0's (``"version": 1``, no
    ``schema``) with 4 of 8 episodes, and there are no records in ``run/``."""
    for learner, seed in JOBS.items():
        d = storage.read_pickle(storage.checkpoint_path(DATA / "run", learner, seed))
        assert "schema" not in d and d["version"] == 1 and storage.checkpoint_schema(d) == 1
        assert len(d["rows"]) == RESUMED_AT and d["episodes"] == 8 and not d["done"]
    names = {p.name for p in (DATA / "run").iterdir()}
    assert names == {"config.toml", "reference.pkl", "jobs"}


def test_cli_resume_exits_2_naming_the_version_and_writes_nothing(old_run):
    before = snapshot(old_run)
    for extra in ([], ["--episodes", "10"]):  # extending the budget is refused the same way
        res = runner.invoke(app, ["run", "--resume", "--out", str(old_run), "-q", *extra])
        assert res.exit_code == 2, res.output
        assert res.exception is None or isinstance(res.exception, SystemExit), res.exception
        text = " ".join(res.output.split())
        assert "Traceback" not in text
        assert "written by mpcmobo 0.1.0" in text and "schema 1" in text, text
        assert (
            f"mpcmobo {mpcmobo.__version__} resumes only its own checkpoints (schema {storage.CHECKPOINT_SCHEMA})"
            in text
        ), text
        # what to do: read the records, or start a new run from the saved settings
        assert f"mpcmobo plot {old_run}" in text and f"mpcmobo evaluate {old_run}" in text
        assert "start a new run" in text and "config.toml" in text
        assert snapshot(old_run) == before  # not a file written, touched or removed


def test_run_study_refuses_to_resume_it(old_run):
    before = snapshot(old_run)
    with pytest.raises(OlderRunError, match=r"mpcmobo 0\.1\.0 \(checkpoint schema 1\)"):
        run_study(None, old_run, resume=True)
    longer = load_settings(old_run / "config.toml", episodes=10)
    with pytest.raises(OlderRunError):  # before the larger budget is saved
        run_study(longer, old_run, resume=True)
    assert snapshot(old_run) == before


def test_its_checkpoints_are_read_for_their_rows(old_run):
    """The rows and incumbents of a schema-1 checkpoint are read as they were written (the
    columns added since are NaN, ``identified`` empty)."""
    run_dir = RunDirectory(old_run)
    settings = run_dir.saved_settings(for_records=True)
    for learner, seed in JOBS.items():
        ckpt = run_dir.checkpoint(learner, seed)
        raw = storage.read_pickle(storage.checkpoint_path(old_run, learner, seed))
        assert ckpt.schema == 1 and len(ckpt.rows) == RESUMED_AT
        for row, d in zip(ckpt.rows, raw["rows"], strict=True):
            got = row.to_dict()
            added = {
                "start_cost",
                "identified",
                "plant_cost",
                "excess_cost",
                "predicted_cost",
                "refused",
                "refused_theta",
            }
            assert set(got) == set(d) | added
            assert got["identified"] == got["refused_theta"] == [] and got["refused"] == ""
            assert all(np.isnan(got[k]) for k in added - {"identified", "refused", "refused_theta"})
            np.testing.assert_equal({k: got[k] for k in d}, d)  # NaN equal to NaN
    incumbents = run_dir.incumbents(settings)
    assert [(n, s, k) for n, s, k, _ in incumbents] == [("mpc-rl", 0, 4), ("mobo", 0, 4)]
    for learner, _, _, theta in incumbents:
        np.testing.assert_array_equal(theta, run_dir.checkpoint(learner, 0).rows[-1].incumbent)


def test_plot_draws_the_figures_of_an_old_run(old_records):
    """``mpcmobo plot`` on the records 0.1.0 left (``episodes.parquet``,
    ``trajectories.parquet``; no ``summary.json`` in the fixture) draws figures 1-4."""
    res = runner.invoke(app, ["plot", str(old_records)])
    assert res.exit_code == 0, f"{res.output}\n{res.exception!r}"
    for name in FIGURES:
        for ext in ("png", "pdf"):
            p = old_records / "figures" / f"{name}.{ext}"
            assert p.exists() and p.stat().st_size > 1000, p


def _table(output: str) -> dict[str, list[str]]:
    """The rows of ``mpcmobo evaluate``'s table by learner: [seed, episodes, J_eval, gap]."""
    rows = {}
    for line in output.splitlines():
        cells = [c.strip() for c in line.strip("│").split("│")]
        if line.startswith("│") and cells[0] in JOBS:
            rows[cells[0]] = cells[1:]
    return rows


def test_evaluate_prints_the_J_eval_of_the_saved_incumbents(old_records):
    """``mpcmobo evaluate`` reads the old run's settings (2 evaluation starts of seed 2025, 10
    steps) and its checkpoints' incumbents: J* and J(theta0) are 0.1.0's own reference values,
    and mobo's incumbent (theta0's, evaluated by 0.1.0 at episode 0) has the J_eval that
    version recorded."""
    reference = storage.read_pickle(old_records / "reference.pkl")
    res = runner.invoke(app, ["evaluate", str(old_records)])
    assert res.exit_code == 0, res.output
    text = " ".join(res.output.split())
    assert f"J* = {reference['J_star']:.5g}, J(theta0) = {reference['J_initial']:.5g}" in text
    rows = _table(res.output)
    assert set(rows) == set(JOBS)
    for learner in JOBS:
        seed, episodes, J, _gap = rows[learner]
        assert (seed, episodes) == ("0", str(RESUMED_AT))
        assert np.isfinite(float(J))
    ckpt = RunDirectory(old_records).checkpoint("mobo", 0)
    assert all(np.array_equal(r.incumbent, ckpt.rows[0].incumbent) for r in ckpt.rows)
    assert rows["mobo"][2] == f"{ckpt.rows[0].J_eval_incumbent:.5g}"


def test_evaluate_reads_an_old_run_whose_options_this_version_renamed(old_records):
    """A 0.1.0 run that wrote MPC-RL's options as that version named them (``lr``,
    ``optimizer = "adam"``: its defaults, so the same run) is evaluated like the fixture:
    evaluating needs no learner options."""
    plain = runner.invoke(app, ["evaluate", str(old_records)])
    assert plain.exit_code == 0, plain.output
    config = old_records / "config.toml"
    config.write_text(
        config.read_text() + '\n[learner_options.mpc-rl]\noptimizer = "adam"\nlr = 0.03\n'
    )
    res = runner.invoke(app, ["evaluate", str(old_records)])
    assert res.exit_code == 0, res.output
    assert _table(res.output) == _table(plain.output)
