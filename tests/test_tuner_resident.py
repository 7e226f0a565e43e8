"""The tuner's process (``mpcmobo serve``): ask, tell and retract answered from memory; a tell
answered once its log is checked, the learning after it; what it records equals a tuner told
directly; a crash between the check and the learning loses nothing; a failed learning is
reported and the trial is pending again; the commands work without it."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pandas as pd
import pytest
from test_tuner_checks import episode
from typer.testing import CliRunner

from mpcmobo.cli import app, resident
from mpcmobo.cli.resident import ADDRESS_FILE, KEY_FILE, Resident, ResidentError, request
from mpcmobo.experiment.tuner import Tuner, write_log

SETTINGS = {"episodes": 4, "steps": 8, "start_mode": "cycle", "n_cycle_starts": 2}
SRC = str(Path(__file__).resolve().parents[1] / "src")
runner = CliRunner()


def _records(path):
    """episodes.parquet without the wall times."""
    df = pd.read_parquet(path / "episodes.parquet")
    return df.drop(columns=[c for c in df.columns if c.endswith("time_s")])


def _log_of(directory: Path, trial: dict, out: Path) -> Path:
    """The episode of the asked ``trial`` (its JSON) on the simulated plant, as a CSV."""
    tuner = Tuner.load(directory)
    asked = tuner.ask()
    assert asked.id == trial["id"]
    return write_log(out, *episode(tuner, asked), tuner.system)


class Served:
    """A :class:`Resident` answering in a thread of this process; ``heard``: its log."""

    def __init__(self, directory: Path) -> None:
        self.heard: list[str] = []
        self.resident = Resident(directory, self.heard.append)
        self.resident.open()
        self.thread = threading.Thread(target=self._serve, daemon=True)
        self.thread.start()

    def _serve(self) -> None:
        try:
            self.resident.serve()
        except OSError:  # the listener closed by stop()
            pass

    def stop(self) -> None:
        with self.resident.lock:  # the background work done
            pass
        self.resident.close()


@pytest.fixture
def made(tmp_path):
    """A new lq tuner (mpc-rl) with no trial asked yet."""
    Tuner("lq", "mpc-rl", tmp_path / "t", **SETTINGS)
    return tmp_path / "t"


def _ask(d: Path) -> dict:
    res = runner.invoke(app, ["ask", str(d)])
    assert res.exit_code == 0, res.output
    return json.loads(res.stdout[res.stdout.index("{") :])


def test_a_served_tuner_records_what_a_tuner_told_directly_records(made, tmp_path):
    """Three trials through ask and tell with the process serving: each tell answers before
    the learning (status says which trial is learned from), ask waits for it and prints the
    next trial, and the records equal those of a tuner told the same logs in Python."""
    direct = Tuner("lq", "mpc-rl", tmp_path / "direct", **SETTINGS)
    served = Served(made)
    try:
        for k in range(3):
            trial = _ask(made)
            assert trial["id"] == k
            log = _log_of(made, trial, tmp_path / f"trial-{k}.csv")
            gate = threading.Event()
            learn = served.resident.tuner.learn

            def held(*a, _learn=learn, _gate=gate, **kw):
                _gate.wait(30)  # the learning waits until the tell has answered
                return _learn(*a, **kw)

            served.resident.tuner.learn = held
            res = runner.invoke(app, ["tell", str(made), str(k), str(log)])
            assert res.exit_code == 0, res.output
            assert f"trial {k} told: plant cost" in res.output, res.output
            st = json.loads(runner.invoke(app, ["status", str(made), "--json"]).stdout)
            assert st["learning"] == k and f"trial {k} is told" in st["recommendation"]["reason"]
            gate.set()
            d = direct.ask()
            direct.tell(d, *episode(direct, d))
        assert _ask(made)["id"] == 3
    finally:
        served.stop()
    assert any("trial 2 learned from" in h for h in served.heard)
    pd.testing.assert_frame_equal(_records(made), _records(tmp_path / "direct"))
    assert not (made / ADDRESS_FILE).exists() and not (made / KEY_FILE).exists()


def test_the_last_trial_of_the_budget_says_so_while_it_is_learned_from(tmp_path):
    """With the process serving, the tell of the budget's last trial says that it was the last;
    an ask meanwhile is refused at once (the learning would end in the same refusal), and the
    status recommends to stop."""
    d = tmp_path / "one"
    Tuner("lq", "mpc-rl", d, **{**SETTINGS, "episodes": 1})
    served = Served(d)
    gate = threading.Event()
    try:
        log = _log_of(d, _ask(d), tmp_path / "trial-0.csv")
        learn = served.resident.tuner.learn

        def held(*a, **kw):
            gate.wait(30)
            return learn(*a, **kw)

        served.resident.tuner.learn = held
        res = runner.invoke(app, ["tell", str(d), "0", str(log)])
        assert res.exit_code == 0 and "the last trial of the budget" in res.output, res.output
        t0 = time.perf_counter()
        res = runner.invoke(app, ["ask", str(d)])
        assert res.exit_code == 2 and "budget of 1 trials is spent" in res.output, res.output
        assert time.perf_counter() - t0 < 20 and not gate.is_set()
        st = json.loads(runner.invoke(app, ["status", str(d), "--json"]).stdout)
        assert st["recommendation"]["action"] == "stop", st["recommendation"]
    finally:
        gate.set()
        served.stop()
    assert Tuner.load(d).episodes == 1


def test_a_crash_between_the_check_and_the_learning_loses_nothing(made, tmp_path):
    """A log accepted (Tuner.accept) by a process that then dies is learned from at the next
    load: the same records as a tell."""
    direct = Tuner("lq", "mpc-rl", tmp_path / "direct", **SETTINGS)
    d = direct.ask()
    direct.tell(d, *episode(direct, d))
    tuner = Tuner.load(made)
    trial = tuner.ask()
    tuner.accept(trial, *episode(tuner, trial))
    assert tuner.status()["learning"] == 0 and (made / "accepted" / "trial-0.pkl").exists()
    reason = tuner.status()["recommendation"]["reason"]  # in Python, before Tuner.learn()
    assert "the tuner's process is learning" not in reason and "Tuner.learn()" in reason, reason
    del tuner  # the process is gone before it learned
    heard: list[str] = []
    resident = Resident(made, heard.append)  # a serve started now says why it takes a while
    resident.open()
    assert resident.lock.acquire(timeout=120)  # its next trial prepared in the background
    resident.lock.release()
    resident.close()
    assert heard[0].startswith("a told log waits: learning from it before serving")
    again = Tuner.load(made)
    assert again.episodes == 1 and again.learning is None
    assert not list((made / "accepted").glob("*.pkl"))
    pd.testing.assert_frame_equal(_records(made), _records(tmp_path / "direct"))


def test_status_after_a_tell_killed_before_its_learning_names_the_command_that_learns(made):
    """A tell killed between its check and its learning, with no process serving the tuner
    (none named, or the one ``resident.json`` names is gone): ``status`` says that the log is
    accepted and not learned from yet and names the command that learns from it, not that a
    process learns; that command does."""
    tuner = Tuner.load(made)
    trial = tuner.ask()
    tuner.accept(trial, *episode(tuner, trial))
    del tuner  # killed before it learned
    gone = subprocess.run(
        [sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True
    )
    for named in (False, True):
        if named:  # a process killed while it served: its files stay
            where = {"socket": str(made / "resident.sock"), "pid": int(gone.stdout)}
            (made / ADDRESS_FILE).write_text(json.dumps(where))
            (made / KEY_FILE).write_bytes(b"key")
        st = json.loads(runner.invoke(app, ["status", str(made), "--json"]).stdout)
        reason = st["recommendation"]["reason"]
        assert st["learning"] == 0 and "the tuner's process is learning" not in reason, reason
        assert "is accepted (accepted/trial-0.pkl) and not learned from yet" in reason, reason
        assert f"mpcmobo ask {made} learns from it and prints the next trial" in reason, reason
    (made / ADDRESS_FILE).unlink()
    assert _ask(made)["id"] == 1 and Tuner.load(made).episodes == 1


def test_a_log_kept_by_a_process_killed_before_it_wrote_the_status_is_not_asked_again(
    made, monkeypatch
):
    """A process (a tell, ``mpcmobo serve``) killed after it kept the log in ``accepted/`` and
    before it wrote ``status.json`` again: ``status`` says that the log is accepted and not
    learned from yet, not that the trial is to be run on the plant, and ``ask`` learns from
    it and prints the next trial, not the told one."""
    tuner = Tuner.load(made)
    trial = tuner.ask()
    assert _ask(made)["id"] == 0  # the trial written for ask, as a tell prepares it
    with monkeypatch.context() as m:
        m.setattr(Tuner, "_write_status", lambda self: None)  # killed before it
        tuner.accept(trial, *episode(tuner, trial))
    del tuner
    st = json.loads(runner.invoke(app, ["status", str(made), "--json"]).stdout)
    reason = st["recommendation"]["reason"]
    assert st["learning"] == 0 and "run it on the plant" not in reason, reason
    assert "is accepted (accepted/trial-0.pkl) and not learned from yet" in reason, reason
    assert _ask(made)["id"] == 1 and Tuner.load(made).episodes == 1


class _Gone:
    """A connection to a tuner's process killed while it answers: the answer never comes."""

    def __enter__(self) -> _Gone:
        return self

    def __exit__(self, *exc: object) -> None:
        return None

    def send(self, obj: object) -> None:
        pass

    def recv(self) -> object:
        raise EOFError


def test_a_process_killed_while_it_answers_is_named_with_where_to_look(made, monkeypatch):
    """The tuner's process dies before its answer: the command's error names what happened
    (the closed connection) and the status that shows whether the told log was kept."""
    monkeypatch.setattr(resident, "_connect", lambda directory: _Gone())
    with pytest.raises(ResidentError) as err:
        request(made, "tell", trial=0, log=None, force=False)
    text = str(err.value)
    assert "stopped while it answered (EOFError)" in text, text
    assert f"mpcmobo status {made} shows whether it kept a told log" in text, text


def test_a_failed_learning_is_reported_and_the_trial_is_pending_again(made, tmp_path):
    """The learner fails in the background: the next command says so and the trial can be
    told again; a retract goes through the process too."""
    served = Served(made)
    try:
        trial = _ask(made)
        log = _log_of(made, trial, tmp_path / "trial-0.csv")
        learner = served.resident.tuner.job.run.learner

        def broken(*a, **k):
            raise RuntimeError("the GP fit diverged")

        learner.observe = broken
        assert runner.invoke(app, ["tell", str(made), "0", str(log)]).exit_code == 0
        res = runner.invoke(app, ["ask", str(made)])
        assert res.exit_code == 1, res.output
        assert "learning from trial 0 failed" in res.output and "diverged" in res.output
        assert "pending again" in res.output
        assert _ask(made)["id"] == 0  # reloaded: the learner as saved, the trial pending
        assert runner.invoke(app, ["tell", str(made), "0", str(log)]).exit_code == 0
        assert _ask(made)["id"] == 1
        assert (made / "trials" / "1" / "trial.json").exists()
        res = runner.invoke(app, ["retract", str(made), "0"])
        assert res.exit_code == 0 and "trial 0 is pending again" in res.output, res.output
        assert not (made / "trials" / "1").exists()  # proposed by a learner that saw trial 0
        res = runner.invoke(app, ["tell", str(made), "5", str(log)])
        assert res.exit_code == 2 and "the pending trial is 0" in res.output, res.output
    finally:
        served.stop()


def test_one_process_per_tuner_and_the_commands_work_without_it(made, tmp_path):
    """A second process on the same tuner is refused, as is a command with another key (the
    process goes on); files left by a killed process do not stop the commands (they load the
    tuner themselves)."""
    served = Served(made)
    try:
        with pytest.raises(ResidentError, match="serves .* already"):
            Resident(made, print).open()
        assert request(made, "ping")[1]["pid"] == os.getpid()
        key = (made / KEY_FILE).read_bytes()
        (made / KEY_FILE).write_bytes(b"x" * 32)  # another key: refused, the process goes on
        with pytest.raises(ResidentError, match="refused this command's key"):
            request(made, "ping")
        (made / KEY_FILE).write_bytes(key)
        assert request(made, "ping")[0]
    finally:
        served.stop()
    (made / ADDRESS_FILE).write_text(json.dumps({"socket": str(made / "gone.sock")}))
    (made / KEY_FILE).write_bytes(b"k" * 32)
    assert request(made, "ping") == (False, None)
    assert _ask(made)["id"] == 0


def test_mpcmobo_serve_answers_the_command_line_until_it_is_stopped(made, tmp_path):
    """``mpcmobo serve DIR`` as its own process: a tell on the command line reaches it, and
    SIGTERM (a service manager's stop; Ctrl-C alike) stops it and removes the files that name
    it."""
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([SRC, os.environ.get("PYTHONPATH", "")]))
    cli = [sys.executable, "-m", "mpcmobo.cli"]
    proc = subprocess.Popen(
        [*cli, "serve", str(made)], env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT
    )
    try:
        for _ in range(600):
            if request(made, "ping")[0]:
                break
            assert proc.poll() is None, proc.stdout.read().decode()  # type: ignore[union-attr]
            time.sleep(0.1)
        trial = request(made, "ask")[1]
        log = _log_of(made, trial, tmp_path / "trial-0.csv")
        tell = subprocess.run(
            [*cli, "tell", str(made), "0", str(log)], env=env, capture_output=True, text=True
        )
        assert tell.returncode == 0 and "the tuner's process learns" in tell.stdout, tell.stderr
        assert request(made, "ask")[1]["id"] == 1
    finally:
        proc.send_signal(signal.SIGTERM)
        out = proc.communicate(timeout=60)[0].decode()
    assert proc.returncode == 143, out
    assert "serving the tuner" in out and "trial 0 learned from" in out
    assert not (made / ADDRESS_FILE).exists()


def test_the_process_reloads_a_tuner_changed_under_it(made):
    """A trial told with the Python ``Tuner`` while the process serves the directory: the
    process sees the files change and answers from them, not from its stale tuner."""
    served = Served(made)
    try:
        assert _ask(made)["id"] == 0
        tuner = Tuner.load(made)
        trial = tuner.ask()
        tuner.tell(trial, *episode(tuner, trial))
        assert _ask(made)["id"] == 1
    finally:
        served.stop()
    assert any("reloading" in h for h in served.heard)


def test_serve_stopped_while_it_learns_exits_at_once(made, monkeypatch):
    """A signal that stops ``mpcmobo serve`` while its thread learns (in C++ code, which an
    interpreter shutting down under it aborts): the process exits at once with the signal's
    code (``os._exit``), the accepted log on disk; idle, it exits as any command does."""
    import mpcmobo.cli.plant as plant_cli
    from mpcmobo.cli.resident import _Work
    from mpcmobo.experiment.interrupts import Interrupted

    def serve_then_stop(self):
        self.work = _Work(what="learning from trial 3: the GP 1/2")
        raise Interrupted(signal.SIGTERM)

    exits = []

    def fake_exit(code):
        exits.append(code)
        raise SystemExit(code)

    monkeypatch.setattr(Resident, "open", lambda self: None)
    monkeypatch.setattr(Resident, "serve", serve_then_stop)
    monkeypatch.setattr(plant_cli.os, "_exit", fake_exit)
    monkeypatch.setattr(plant_cli.signal, "signal", lambda *a: None)  # this process's stays
    res = CliRunner().invoke(app, ["serve", str(made)])
    assert exits == [143] and res.exit_code == 143, res.output
    monkeypatch.setattr(
        Resident, "serve", lambda self: (_ for _ in ()).throw(Interrupted(signal.SIGTERM))
    )
    res = CliRunner().invoke(app, ["serve", str(made)])
    assert exits == [143] and res.exit_code == 143  # idle: no os._exit, a normal exit


def test_a_closed_resident_stops_serving_without_an_error(made):
    """``close()`` (the process stopping, from another thread) while ``serve()`` waits in
    ``accept()``, which then fails: the loop ends, where it went on to accept on a listener
    that was gone (an AttributeError)."""
    resident = Resident(made, lambda line: None)

    class Closing:
        address = None

        def accept(self):
            resident.listener = None  # closed meanwhile
            raise OSError("the listener is closed")

        def close(self):
            pass

    resident.listener = Closing()
    resident.serve()  # returns: no AttributeError
    assert resident.listener is None


def test_a_served_tuner_takes_another_exploration_budget(made):
    """``ask --exploration-budget`` answered by the tuner's process: it reloads the tuner with
    the budget, which is saved with the tuner's settings."""
    served = Served(made)
    try:
        res = runner.invoke(app, ["ask", str(made), "--exploration-budget", "2"])
        assert res.exit_code == 0, res.output
        assert served.resident.tuner.settings.exploration.budget == 2.0
    finally:
        served.stop()
    assert Tuner.load(made).settings.exploration.budget == 2.0
    assert any("reloading" in h for h in served.heard)


def test_a_served_tell_with_force_names_the_checks_it_was_told_despite(made, tmp_path):
    """A quarantined log told with --force while the process serves says, as without it,
    which checks it was accepted despite."""
    served = Served(made)
    try:
        trial = _ask(made)
        tuner = Tuner.load(made)
        asked = tuner.ask()
        X, U = episode(tuner, asked, override=(range(2, 6), [2.5]))
        log = write_log(tmp_path / "ep.csv", X, U, tuner.system)
        res = runner.invoke(app, ["tell", str(made), str(trial["id"]), str(log)])
        assert res.exit_code == 2 and "quarantined" in res.output, res.output
        res = runner.invoke(app, ["tell", str(made), str(trial["id"]), "--force"])
        assert res.exit_code == 0, res.output
        assert "trial 0 told (accepted with --force despite: inputs): plant cost" in " ".join(
            res.output.split()
        ), res.output
    finally:
        served.stop()
