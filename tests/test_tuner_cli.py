"""The loop's edges on the command line and in Python: a new tuner needs its system; a log is
read (a semicolon-separated CSV too) and refused before the tuner is loaded; Ctrl-C in a tell
says the trial is pending; export names a pending trial; --force tells the quarantined log; a
System built in Python is recorded so that Tuner.load builds it again, or refused saying how."""

from __future__ import annotations

import importlib
import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from test_tuner_checks import episode
from typer.testing import CliRunner
from user_system_source import SYSTEM

from mpcmobo.cli import app
from mpcmobo.experiment.tuner import Tuner, TunerError, write_log
from mpcmobo.systems import registry

runner = CliRunner()


def _output(res) -> str:
    return " ".join(res.output.split())


def test_a_new_tuner_needs_its_system(tmp_path):
    res = runner.invoke(app, ["ask", str(tmp_path / "t")])
    assert res.exit_code == 2 and "--system NAME" in _output(res), res.output
    assert "--config FILE" in _output(res) and not (tmp_path / "t").exists()
    with pytest.raises(TunerError, match="a new tuner needs its system"):
        Tuner(out=tmp_path / "p")


def test_a_new_tuner_in_a_file_or_a_used_directory_is_a_usage_error(tmp_path):
    """The directory of ask is its argument (no --out): a file, a path under a file or a
    directory with other files is refused with exit code 2, as by the other commands, and
    nothing is written."""
    a_file = tmp_path / "file"
    a_file.write_text("x")
    used = tmp_path / "used"
    used.mkdir()
    (used / "notes.txt").write_text("mine")
    cases = {a_file: "is a file", a_file / "t": "is a file", used: "is not empty"}
    for directory, message in cases.items():
        res = runner.invoke(app, ["ask", str(directory), "--system", "lq"])
        assert res.exit_code == 2 and message in _output(res), (directory, res.output)
        assert "--out" not in res.output, res.output
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "used"]
    assert [p.name for p in used.iterdir()] == ["notes.txt"]


@pytest.fixture
def asked(tmp_path):
    """A tuner on lq made by ``mpcmobo ask``, its trial 0 pending, and a true log of it."""
    d = tmp_path / "t"
    res = runner.invoke(app, ["ask", str(d), "--system", "lq", "--learner", "mpc-rl", "-n", "2"])
    assert res.exit_code == 0, res.output
    tuner = Tuner.load(d)
    trial = tuner.ask()
    return d, tuner, trial, episode(tuner, trial)


def test_a_log_is_checked_before_the_tuner_is_loaded(asked, tmp_path, monkeypatch):
    d, tuner, _, (X, U) = asked
    bad = tmp_path / "bad.parquet"
    bad.write_bytes(b"not parquet")
    renamed = tmp_path / "renamed.csv"
    write_log(renamed, X, U, tuner.system)
    df = pd.read_csv(renamed).rename(columns={"p": "pos"})
    df.to_csv(renamed, index=False)

    def loaded(*args, **kwargs):
        raise AssertionError("the tuner was loaded")

    as_json = tmp_path / "ep.json"
    pd.read_csv(renamed).to_json(as_json)
    monkeypatch.setattr(Tuner, "load", loaded)
    for log, message in [
        (tmp_path / "missing.csv", "does not exist"),
        (bad, "cannot be read"),
        (as_json, "is a JSON file: a log is a CSV file .* or a Parquet file"),
        (renamed, "no column 'p'; .* its columns are \\['pos', 'v', 'f'\\]"),
    ]:
        res = runner.invoke(app, ["tell", str(d), "0", str(log)])
        assert res.exit_code == 2, res.output
        assert re.search(message, _output(res)), res.output


def test_a_semicolon_separated_log_is_read(asked, tmp_path):
    d, tuner, _, (X, U) = asked
    log = tmp_path / "ep.csv"
    write_log(log, X, U, tuner.system)
    pd.read_csv(log).to_csv(log, sep=";", index=False)
    assert ";" in log.read_text()
    res = runner.invoke(app, ["tell", str(d), "0", str(log)])
    assert res.exit_code == 0 and "trial 0 told" in res.output, res.output


def test_a_log_with_decimal_commas_is_read(asked, tmp_path):
    """A semicolon-separated CSV with decimal commas, as spreadsheets in many locales write
    it: the same numbers as the log with decimal points."""
    from mpcmobo.experiment.plantlog import read_log_file

    d, tuner, _, (X, U) = asked
    log = tmp_path / "ep.csv"
    write_log(log, X, U, tuner.system)
    dots = pd.read_csv(log)
    comma = tmp_path / "comma.csv"
    dots.to_csv(comma, sep=";", decimal=",", index=False)
    assert "," in comma.read_text()
    pd.testing.assert_frame_equal(read_log_file(comma), dots)
    res = runner.invoke(app, ["tell", str(d), "0", str(comma)])
    assert res.exit_code == 0 and "trial 0 told" in res.output, res.output


def test_ctrl_c_in_a_tell_says_the_trial_is_pending(asked, tmp_path, monkeypatch):
    d, tuner, _, (X, U) = asked
    log = write_log(tmp_path / "ep.csv", X, U, tuner.system)

    def interrupted(self, *args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(Tuner, "tell", interrupted)
    res = runner.invoke(app, ["tell", str(d), "0", str(log)])
    assert res.exit_code == 130 and "trial 0 is still pending" in _output(res), res.output
    monkeypatch.undo()
    assert Tuner.load(d).status()["pending"] == 0


def test_ctrl_c_that_a_library_turns_into_another_error_still_says_the_trial_is_pending(
    asked, tmp_path, monkeypatch
):
    """BoTorch restores a GP's state when its fit is interrupted; where that fails it raises a
    RuntimeError in place of the KeyboardInterrupt: still the Ctrl-C, not a crash."""
    d, tuner, _, (X, U) = asked
    log = write_log(tmp_path / "ep.csv", X, U, tuner.system)

    def interrupted_fit(self, *args, **kwargs):
        try:
            raise KeyboardInterrupt
        except KeyboardInterrupt:
            raise RuntimeError("Unexpected key(s) in state_dict") from None

    monkeypatch.setattr(Tuner, "tell", interrupted_fit)
    res = runner.invoke(app, ["tell", str(d), "0", str(log)])
    assert res.exit_code == 130 and "trial 0 is still pending" in _output(res), res.output

    def failed(self, *args, **kwargs):
        raise RuntimeError("a failure of its own")

    monkeypatch.setattr(Tuner, "tell", failed)
    res = runner.invoke(app, ["tell", str(d), "0", str(log)])
    assert res.exit_code == 1 and isinstance(res.exception, RuntimeError), res.output
    monkeypatch.undo()
    assert Tuner.load(d).status()["pending"] == 0


def test_ctrl_c_while_the_next_trial_is_prepared_says_the_trial_is_told(
    asked, tmp_path, monkeypatch
):
    from mpcmobo.cli import plant

    d, tuner, _, (X, U) = asked
    log = write_log(tmp_path / "ep.csv", X, U, tuner.system)

    def interrupted(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(plant, "_write_trial", interrupted)
    res = runner.invoke(app, ["tell", str(d), "0", str(log)])
    assert res.exit_code == 130, res.output
    assert "trial 0 is told and recorded" in _output(res) and "mpcmobo ask" in _output(res)
    monkeypatch.undo()
    status = Tuner.load(d).status()
    assert status["pending"] is None and [t["id"] for t in status["trials"]] == [0]


def test_export_names_a_pending_trial_and_force_tells_the_quarantined_log(asked, tmp_path):
    d, tuner, trial, _ = asked
    res = runner.invoke(app, ["export", str(d), "--out", str(tmp_path / "c")])  # deployed
    assert res.exit_code == 2 and "no trial of" in _output(res), res.output
    assert "is told yet" in _output(res) and "job" not in _output(res)  # a tuner's words
    res = runner.invoke(app, ["export", str(d), "--theta", "0", "--out", str(tmp_path / "c")])
    assert res.exit_code == 2 and "trial 0 is pending" in _output(res), res.output
    assert "(written by ask)" in _output(res)  # mpcmobo ask wrote it
    (d / "trials" / "0" / "controller.casadi").unlink()  # as for a trial connect asked for
    res = runner.invoke(app, ["export", str(d), "--theta", "0", "--out", str(tmp_path / "c")])
    assert res.exit_code == 2 and f"mpcmobo ask {d} writes its controller" in _output(res)
    X, U = episode(tuner, trial, override=(range(2, 7), [2.5]))
    log = write_log(tmp_path / "ep.csv", X, U, tuner.system)
    res = runner.invoke(app, ["tell", str(d), "0", str(log)])
    assert res.exit_code == 2 and "quarantined" in _output(res), res.output
    assert "steps 2-6: an operator override" in _output(res)
    res = runner.invoke(app, ["tell", str(d), "0"])
    assert res.exit_code == 2 and "--force" in _output(res), res.output
    res = runner.invoke(app, ["tell", str(d), "0", "--force"])
    assert res.exit_code == 0, res.output
    assert "trial 0 told (accepted with --force despite: inputs)" in _output(res)
    res = runner.invoke(app, ["status", str(d), "--json"])
    st = json.loads(res.output)
    assert st["quarantined"] == [] and st["told"] == 1 and st["trials"][0]["id"] == 0


def test_a_system_object_is_recorded_or_refused(tmp_path, monkeypatch):
    (tmp_path / "fourtank_like.py").write_text(SYSTEM)
    monkeypatch.syspath_prepend(str(tmp_path))
    module = importlib.import_module("fourtank_like")
    with pytest.raises(TunerError, match="path_constraints .* a function or lambda.*make_system"):
        Tuner(module.make_system(), "mpc-rl", tmp_path / "lambda", episodes=2)
    assert not (tmp_path / "lambda").exists()
    system = module.make_system(path=False)
    out = tmp_path / "t"
    tuner = Tuner(system, "mpc-rl", out, episodes=2, evaluation={"n_starts": 1})
    trial = tuner.ask()
    tuner.tell(trial, *episode(tuner, trial))
    monkeypatch.delitem(registry._REGISTRY, system.name)  # as in another process
    assert Tuner.load(out).episodes == 1
    monkeypatch.delitem(registry._REGISTRY, system.name)
    res = runner.invoke(app, ["status", str(out)])
    assert res.exit_code == 0 and "1 of 2 trials told" in res.output, res.output
    # another process, elsewhere, without the module's directory on its path: found where it
    # was when the tuner was made
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[1] / "src")}
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    cmd = [sys.executable, "-m", "mpcmobo.cli", "ask", str(out)]
    proc = subprocess.run(cmd, cwd=elsewhere, env=env, capture_output=True, text=True)
    assert proc.returncode == 0 and '"id": 1' in proc.stdout, proc.stderr[-2000:]


def test_status_says_when_the_fit_no_longer_follows_the_trials(capsys):
    """Once tuning has converged the learner fits no later trial: the identification's line
    says so, where the count of transitions would otherwise look stale."""
    import mpcmobo.cli as cli
    from mpcmobo.cli import plant

    ident = {
        "parameters": {"a": {"nominal": 0.15, "estimate": 0.24, "std": 0.002}},
        "holdout_error": 0.01,
        "nominal_error": 0.2,
        "transitions": 425,
    }
    for frozen in (False, True):
        with cli.console.capture() as out:
            plant._print_identification(ident, frozen=frozen)
        text = " ".join(out.get().split())
        assert "fitted on 425 transitions" in text
        assert ("the trials since are not fitted" in text) == frozen
        assert "fitted again" not in text  # a status saved before it said when
    with cli.console.capture() as out:
        plant._print_identification({**ident, "refit_growth": 0.1})
    text = " ".join(out.get().split())
    assert "fitted on 425 transitions" in text  # fewer than told: the fit waits for growth
    assert "(fitted again once the transitions have grown by 10%)" in text


def test_a_study_of_one_learner_and_seed_is_not_taken_for_a_tuner(tmp_path):
    """``ask``, ``status`` and ``Tuner.load`` on the directory of ``mpcmobo run`` with one
    learner and one seed are refused, naming how to go on with it and where its results are;
    nothing is written into it."""
    from mpcmobo.experiment.settings import load_settings
    from mpcmobo.experiment.study import run_study

    out = tmp_path / "study"
    s = load_settings(
        None,
        system={"name": "lq"},
        learners=["identify"],
        seeds=[0],
        episodes=1,
        steps=5,
        workers=1,
        evaluation={"n_starts": 1},
    )
    run_study(s, out)
    before = sorted(p.relative_to(out) for p in out.rglob("*"))
    for args in (["status", str(out)], ["ask", str(out)], ["ask", str(out), "--system", "lq"]):
        res = runner.invoke(app, args)
        text = _output(res)
        assert res.exit_code == 2, text
        assert "holds a study of mpcmobo run" in text and "mpcmobo run --resume" in text
    with pytest.raises(TunerError, match="not a tuner"):
        Tuner.load(out)
    assert sorted(p.relative_to(out) for p in out.rglob("*")) == before
