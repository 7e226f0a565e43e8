"""Damaged run files, bad output paths and bad learner options: a clear error naming
the file or option and the fix (exit 1 or 2, no traceback), a fallback to the previous
checkpoint generation, and nothing created when a run cannot start."""

from __future__ import annotations

import json
import re

import pandas as pd
import pytest
from typer.testing import CliRunner

from mpcmobo.cli import app
from mpcmobo.experiment import storage
from mpcmobo.experiment.settings import load_settings
from mpcmobo.experiment.study import run_study

runner = CliRunner()
WALL = ["mpc_time_s", "learner_time_s", "eval_time_s"]
SMALL = [
    "--system",
    "lq",
    "--learner",
    "mpc-rl",
    "--episodes",
    "4",
    "--steps",
    "6",
    "--workers",
    "1",
    "-q",
    "--no-plot",
]


def small(**kw):
    base = dict(system={"name": "lq"}, learners=["mpc-rl"], episodes=4, steps=6, workers=1)
    return load_settings(None, **(base | kw))


@pytest.fixture(scope="module")
def full(tmp_path_factory):
    out = tmp_path_factory.mktemp("full") / "run"
    run_study(small(), out)
    return storage.read_episodes(out).drop(columns=WALL)


@pytest.fixture
def partial(tmp_path):
    """A run interrupted after 3 of its 4 episodes."""
    out = tmp_path / "run"
    run_study(small(), out, max_episodes_this_call=3)
    return out


def no_traceback(res) -> None:
    assert "Traceback" not in res.output
    assert res.exception is None or isinstance(res.exception, SystemExit), res.exception


DAMAGE = {
    "garbage": b"this is not a pickle",
    "truncated": None,  # the first half of the real file
    "empty": b"",
}


@pytest.mark.parametrize("damage", list(DAMAGE))
def test_damaged_checkpoint_falls_back_to_the_previous_generation(full, partial, damage):
    ck = storage.checkpoint_path(partial, "mpc-rl", 0)
    prev = storage.previous_checkpoint_path(partial, "mpc-rl", 0)
    assert prev.exists()  # the generation before the latest is kept
    data = ck.read_bytes()
    ck.write_bytes(DAMAGE[damage] if DAMAGE[damage] is not None else data[: len(data) // 2])
    res = runner.invoke(app, ["run", "--resume", "--out", str(partial), "-q", "--no-plot"])
    assert res.exit_code == 0, res.output
    no_traceback(res)
    assert "checkpoint.pkl cannot be read" in res.output and "previous checkpoint" in res.output
    assert (ck.parent / "checkpoint.pkl.damaged").read_bytes() != data  # kept, not lost
    pd.testing.assert_frame_equal(storage.read_episodes(partial).drop(columns=WALL), full)


def test_no_readable_checkpoint_names_the_file_and_the_fix(partial):
    storage.checkpoint_path(partial, "mpc-rl", 0).write_bytes(b"")
    storage.previous_checkpoint_path(partial, "mpc-rl", 0).write_bytes(b"\x80\x05junk")
    res = runner.invoke(app, ["run", "--resume", "--out", str(partial), "-q"])
    assert res.exit_code == 1, res.output
    no_traceback(res)
    assert "checkpoint.pkl cannot be read" in res.output
    assert re.search(r"delete \S+mpc-rl-s0", res.output.replace("\n", ""))


def test_damaged_reference_names_the_file_and_the_fix(full, partial):
    (partial / "reference.pkl").write_bytes(b"\x80\x05garbage")
    res = runner.invoke(app, ["run", "--resume", "--out", str(partial), "-q"])
    assert res.exit_code == 1, res.output
    no_traceback(res)
    assert "reference.pkl cannot be read" in res.output and "delete it" in res.output
    (partial / "reference.pkl").unlink()  # the fix: J* is computed again, nothing else changes
    res = runner.invoke(app, ["run", "--resume", "--out", str(partial), "-q", "--no-plot"])
    assert res.exit_code == 0, res.output
    pd.testing.assert_frame_equal(storage.read_episodes(partial).drop(columns=WALL), full)


def test_damaged_config_and_records_name_the_file(partial):
    (partial / "episodes.parquet").write_bytes(b"PAR1 not really")
    res = runner.invoke(app, ["plot", str(partial)])
    assert res.exit_code == 1, res.output
    no_traceback(res)
    assert "episodes.parquet cannot be read" in res.output and "--resume" in res.output
    (partial / "config.toml").write_text("episodes = = 3\n")
    for args in (["run", "--resume", "--out", str(partial), "-q"], ["evaluate", str(partial)]):
        res = runner.invoke(app, args)
        assert res.exit_code == 2, res.output
        no_traceback(res)
        assert "config.toml" in res.output and "not valid TOML" in res.output
    (partial / "config.toml").write_text("episodes = 4\nsystem = 3\n")  # a table that is not
    for args in (["run", "--resume", "--out", str(partial), "-q"], ["evaluate", str(partial)]):
        res = runner.invoke(app, args)
        assert res.exit_code == 2, res.output
        no_traceback(res)
        assert "system: Input should be a valid dictionary" in res.output


def test_evaluate_without_a_finished_episode_is_an_error(tmp_path):
    out = tmp_path / "run"
    run_study(small(), out, max_episodes_this_call=0)
    res = runner.invoke(app, ["evaluate", str(out)])
    assert res.exit_code == 1, res.output
    assert "nothing to evaluate" in res.output and "J*" not in res.output


def test_bad_out_paths_are_clear_errors_and_create_nothing(tmp_path):
    a_file = tmp_path / "file"
    a_file.write_text("x")
    cases = {
        str(a_file): "is a file",
        str(a_file / "run"): "is a file",
        str(tmp_path / "missing" / "deeper" / "run"): "does not exist",  # one level is made
        "/proc/mpcmobo-cannot-write-here": "cannot",
    }
    for out, message in cases.items():
        res = runner.invoke(app, ["run", *SMALL, "--out", out])
        assert res.exit_code == 2, (out, res.output)
        no_traceback(res)
        assert message in res.output, (out, res.output)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]
    res = runner.invoke(app, ["run", "--resume", "--out", str(tmp_path / "nope")])
    assert res.exit_code == 2 and "nothing to resume" in res.output
    no_traceback(res)
    assert not (tmp_path / "nope").exists()


@pytest.mark.parametrize(
    "learner, options, key, message",
    [
        ("mpc-rl", "lr_rate = 0.1", "lr_rate", "unknown option"),
        ("mpc-rl", 'optimizer = {lr = "big"}', "optimizer.lr", "valid number (got 'big')"),
        ("mpc-rl", 'optimizer = {rule = "gd", lr = -1.0}', "optimizer.lr", "greater than 0"),
        ("mpc-rl", 'deploy = "pooled"', "deploy", "'verified', 'iterate'"),
        ("bo", "deploy = {confidence = 1.5}", "deploy.confidence", "less than 1 (got 1.5)"),
        ("bo", 'deploy = {rule = "incumbent", min_runs = 3}', "deploy.min_runs", "unknown"),
        ("mobo", "search = {num_restarts = 0}", "search.num_restarts", "greater than or equal"),
        ("mobo", "context = 'none'", "context", "unknown option"),
        ("hybrid", "gradient_every = 0", "gradient_every", "greater than or equal to 1"),
    ],
)
def test_bad_learner_options_exit_2_naming_the_option(tmp_path, learner, options, key, message):
    """A bad option in a settings file: exit 2 before anything is written, one message that
    names the option as ``learner_options.NAME.key`` and lists the learner's options with their
    defaults."""
    cfg = tmp_path / "c.toml"
    cfg.write_text(f"[learner_options.{learner}]\n{options}\n")
    res = runner.invoke(app, ["run", *SMALL, "--config", str(cfg), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2, res.output
    no_traceback(res)
    text = " ".join(res.output.split())
    assert f"learner_options.{learner}.{key}: " in text, text
    assert message in text, text
    assert f"the options of '{learner}' (with their defaults)" in text
    assert "unexpected keyword" not in text  # validated, not passed on to a constructor
    if learner == "mpc-rl":
        assert "optimizer = {'rule': 'adam', 'lr': 0.03, 'max_step': 0.1}" in text
    else:
        assert "n_init = 5" in text and "'confidence': 0.9" in text
    assert not (tmp_path / "o").exists()


def test_a_bad_trust_region_option_is_named_by_its_dotted_path(tmp_path):
    """An option inside the ``trust_region`` table (a table or ``false``) is named like any
    other: ``learner_options.bo.trust_region.length_inti``, one line, without the names of
    the validator's alternatives."""
    cfg = tmp_path / "c.toml"
    cfg.write_text("[learner_options.bo]\ntrust_region = {length_inti = 0.3}\n")
    res = runner.invoke(app, ["run", *SMALL, "--config", str(cfg), "--out", str(tmp_path / "o")])
    assert res.exit_code == 2, res.output
    no_traceback(res)
    text = " ".join(res.output.split())
    assert "learner_options.bo.trust_region.length_inti: unknown option" in text, text
    assert "function-after" not in text and "literal[False]" not in text, text
    assert not (tmp_path / "o").exists()


def test_run_help_shows_defaults_and_learner_options():
    res = runner.invoke(app, ["run", "--help"], terminal_width=200)
    assert res.exit_code == 0
    text = " ".join(res.output.replace("│", " ").split())  # an option's default may fold
    assert re.search(r"episodes per job \[default: \(?600\)?\]", text), text
    assert re.search(r"parallel processes \[default: \(?2\)?\]", text), text
    # every learner's options with their defaults, as TOML
    assert 'optimizer = {rule = "adam", lr = 0.03, max_step = 0.1}' in text, text
    assert 'deploy = {rule = "evidence", confidence = 0.9, min_runs = 6}' in text
    assert "n_init = 5" in text and "gradient_every = 3" in text
    for name in ("mpc-rl", "bo", "mobo", "hybrid"):
        assert f"{name}: " in text


def test_summary_counts_the_warnings_logged_in_run_log(tmp_path):
    """Library warnings go to DIR/run.log, not the terminal; summary.json counts them."""
    import warnings

    from mpcmobo.experiment import loop

    original = loop.LearningRun.run_episode

    def noisy(self):
        warnings.warn(
            "Optimization failed within `scipy.optimize.minimize`", RuntimeWarning, stacklevel=1
        )
        return original(self)

    loop.LearningRun.run_episode = noisy
    try:
        res = runner.invoke(app, ["run", *SMALL, "--out", str(tmp_path / "run")])
    finally:
        loop.LearningRun.run_episode = original
    assert res.exit_code == 0, res.output
    assert "Optimization failed" not in res.output
    log = (tmp_path / "run" / "run.log").read_text()
    assert log.count("Optimization failed within") == 4
    assert json.loads((tmp_path / "run" / "summary.json").read_text())["warnings"] == 4


def test_redirected_output_prints_progress_lines(tmp_path):
    """Not a terminal (CliRunner): one plain line per job every few episodes."""
    args = [a for a in SMALL if a != "-q"]
    res = runner.invoke(app, ["run", *args, "--episodes", "20", "--out", str(tmp_path / "r")])
    assert res.exit_code == 0, res.output
    lines = [ln for ln in res.output.splitlines() if "mpc-rl s0: episode" in ln]
    assert [ln.split("episode ")[1].split(",")[0] for ln in lines] == [
        "1/20",
        "2/20",
        "4/20",
        "6/20",
        "8/20",
        "10/20",
        "12/20",
        "14/20",
        "16/20",
        "18/20",
        "20/20",
    ]
    assert all("best J_eval" in ln for ln in lines)
