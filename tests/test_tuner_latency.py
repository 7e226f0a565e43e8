"""A tuner that answers at once: ``mpcmobo status`` reads status.json without torch, a bad log
is refused before the learner is loaded, and the learner's long work reaches ``tell``'s
progress."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from test_tuner_checks import episode
from test_tuner_writers import _holder
from typer.testing import CliRunner

from mpcmobo.cli import app
from mpcmobo.experiment.tuner import Tuner, TunerError, write_log
from mpcmobo.mpc import export

SRC = str(Path(__file__).resolve().parents[1] / "src")
HEAVY = ("torch", "botorch", "gpytorch", "mpcmobo.experiment.tuner", "mpcmobo.learners.gp")
runner = CliRunner()


@pytest.fixture(scope="module")
def told(tmp_path_factory):
    """A tuner of one told trial and one pending (lq, mpc-rl), and the pending trial's log."""
    base = tmp_path_factory.mktemp("latency")
    tuner = Tuner({"name": "lq", "identify": False}, "mpc-rl", base / "t", episodes=3, steps=6)
    trial = tuner.ask()
    tuner.tell(trial, *episode(tuner, trial))
    trial = tuner.ask()
    log = write_log(base / "trial-1.csv", *episode(tuner, trial), tuner.system)
    return base / "t", log


def _status_in_a_fresh_process(d: Path, *args: str) -> tuple[str, list[str]]:
    """``mpcmobo status d *args``'s output in a new interpreter, and the heavy modules it
    imported."""
    code = (
        "import sys, io, contextlib\n"
        "from mpcmobo.cli import app\n"
        "out = io.StringIO()\n"
        "with contextlib.redirect_stdout(out):\n"
        f"    try: app([*sys.argv[1:]])\n"
        "    except SystemExit as e: assert not e.code, e.code\n"
        f"print(repr([m for m in {HEAVY!r} if m in sys.modules]))\n"
        "print(out.getvalue())\n"
    )
    env = {**os.environ, "PYTHONPATH": SRC, "COLUMNS": "200"}
    proc = subprocess.run(
        [sys.executable, "-c", code, "status", str(d), *args],
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    first, _, rest = proc.stdout.partition("\n")
    return rest, eval(first)  # noqa: S307 - the list printed above


def test_status_reads_status_json_without_torch_and_loads_the_tuner_when_it_is_stale(
    told, tmp_path
):
    d = tmp_path / "t"
    shutil.copytree(told[0], d)
    text, heavy = _status_in_a_fresh_process(d)
    assert heavy == [] and "1 of 3 trials told, trial 1 pending" in text
    as_json, heavy = _status_in_a_fresh_process(d, "--json")
    assert heavy == [] and json.loads(as_json)["pending"] == 1
    assert json.loads(as_json) == json.loads(json.dumps(Tuner.load(d).status()))
    ckpt = next(d.glob("jobs/*/checkpoint.pkl"))
    later = (d / "status.json").stat().st_mtime_ns + 10**9
    os.utime(ckpt, ns=(later, later))  # a tell interrupted after its checkpoint
    stale_text, heavy = _status_in_a_fresh_process(d)
    assert "mpcmobo.experiment.tuner" in heavy and stale_text == text


def test_a_bad_log_is_refused_before_the_learner_is_loaded(told, tmp_path, monkeypatch):
    d = tmp_path / "t"
    shutil.copytree(told[0], d)

    def no_load(*args, **kwargs):
        raise AssertionError("the tuner was loaded")

    monkeypatch.setattr(Tuner, "load", no_load)
    missing = tmp_path / "nosuch.csv"
    res = runner.invoke(app, ["tell", str(d), "1", str(missing)])
    assert res.exit_code == 2 and str(missing) in res.output and "does not exist" in res.output
    bad = tmp_path / "bad.csv"
    bad.write_text("a,b\n1,2\n")
    res = runner.invoke(app, ["tell", str(d), "1", str(bad)])
    assert res.exit_code == 2 and "no column 'p'" in res.output, res.output


def test_the_learners_progress_reaches_tell(told, tmp_path, monkeypatch):
    """Tuner.tell hands its callback to the learner for the tell (and takes it back after);
    the command line's tell shows what the learner reports."""
    d = tmp_path / "t"
    shutil.copytree(told[0], d)
    tuner = Tuner.load(d)
    learner = tuner.job.run.learner
    observe = type(learner).observe

    def reporting(self, *args, **kwargs):
        if self.progress is not None:
            for k in range(1, 4):
                self.progress("twin", k, 3)
        return observe(self, *args, **kwargs)

    monkeypatch.setattr(type(learner), "observe", reporting)
    heard = []
    X, U = episode(tuner, tuner.ask())
    tuner.tell(1, X, U, progress=lambda *a: heard.append(a))
    assert heard == [("twin", 1, 3), ("twin", 2, 3), ("twin", 3, 3)]
    assert tuner.job.run.learner.progress is None

    d2 = tmp_path / "cli"
    shutil.copytree(told[0], d2)
    res = runner.invoke(app, ["tell", str(d2), "1", str(told[1])])
    assert res.exit_code == 0, res.output
    assert "twin: 3/3" in res.output and "trial 1 told" in res.output


def test_tell_prepares_the_next_trial_and_ask_prints_it_without_the_tuner(
    told, tmp_path, monkeypatch
):
    """After ``mpcmobo tell`` the next trial is written (its JSON and controller); ``ask``
    prints that trial without loading the tuner, and it is the trial the tuner asks."""
    d, log = told
    work = tmp_path / "t"
    shutil.copytree(d, work)
    res = runner.invoke(app, ["tell", str(work), "1", str(log)])
    assert res.exit_code == 0, res.output
    assert "trial 2 is ready" in res.output
    assert (work / "trials" / "2" / "controller.casadi").is_file()

    def no_load(*a, **k):
        raise AssertionError("ask loaded the tuner")

    with monkeypatch.context() as m:
        m.setattr(Tuner, "load", no_load)
        res = runner.invoke(app, ["ask", str(work)])
    assert res.exit_code == 0, res.output
    printed = json.loads(res.output)
    assert printed["id"] == 2
    assert printed == Tuner.load(work).ask().to_json()


def test_ask_during_a_tell_waits_for_it_rather_than_print_the_trial_it_tells(
    told, tmp_path, monkeypatch
):
    """While another process changes the tuner (a tell of the prepared trial under way),
    ``ask`` does not print that trial from the files: it loads the tuner, which waits for the
    tell; once the tell is done it prints the prepared trial again without the tuner."""
    d, log = told
    work = tmp_path / "t"
    shutil.copytree(d, work)
    assert runner.invoke(app, ["tell", str(work), "1", str(log)]).exit_code == 0
    loaded: list[Path] = []

    def load(directory, *a, **k):
        loaded.append(directory)
        raise TunerError("loaded")

    holder = _holder(work)  # the other process's tell
    with monkeypatch.context() as m:
        m.setattr(Tuner, "load", load)
        res = runner.invoke(app, ["ask", str(work)])
        holder.communicate("go\n", timeout=30)
        assert res.exit_code == 2 and loaded == [work] and "loaded" in res.output, res.output
        res = runner.invoke(app, ["ask", str(work)])
    assert res.exit_code == 0 and json.loads(res.output)["id"] == 2, res.output


def test_a_trial_s_controller_is_replaced_whole_or_not_at_all(told, tmp_path, monkeypatch):
    """``ask`` writing a trial's controller again (here: killed halfway through it) leaves the
    earlier, complete file, which a plant program may be loading meanwhile, and no part of its
    own; two commands writing it at once do not write into one file."""
    d, _ = told
    work = tmp_path / "t"
    shutil.copytree(d, work)
    assert runner.invoke(app, ["ask", str(work)]).exit_code == 0
    controller = work / "trials" / "1" / "controller.casadi"
    before = controller.read_bytes()

    def killed_halfway(mpc, theta, path):
        Path(path).write_bytes(before[: len(before) // 2])
        raise RuntimeError("killed")

    (work / "status.json").unlink()  # the tuner loaded, the trial written again
    with monkeypatch.context() as m:
        m.setattr(export, "export_casadi", killed_halfway)
        res = runner.invoke(app, ["ask", str(work)])
    assert res.exit_code != 0
    assert controller.read_bytes() == before
    assert sorted(p.name for p in controller.parent.iterdir()) == [
        "controller.casadi",
        "trial.json",
    ]
    assert json.loads(runner.invoke(app, ["ask", str(work)]).output)["id"] == 1
