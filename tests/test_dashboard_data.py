"""The dashboard without a browser: its server answers GET only and binds to 127.0.0.1 by
default; its data are rebuilt only when a file changed; a file that cannot be read becomes a
message; the rows of a job whose checkpoint is newer than the records are the checkpoint's; the
evidence behind a change of the deployed theta; the recorded plant cost is preferred."""

from __future__ import annotations

import http.client
import inspect
import json
import os
import shutil
import signal
import socket
import subprocess
import sys

import numpy as np
import pandas as pd
from dashboard_helpers import serving
from typer.testing import CliRunner

from mpcmobo.cli import app
from mpcmobo.cli.dashboard import dashboard
from mpcmobo.dashboard.files import FileCache, read_parquet
from mpcmobo.dashboard.payload import run_payload
from mpcmobo.dashboard.runs import RunSource
from mpcmobo.dashboard.series import changes, job_series
from mpcmobo.dashboard.server import make_server
from mpcmobo.experiment import storage
from mpcmobo.experiment.rundir import RUNNING_FILE

TEXT = {"capture_output": True, "text": True}


def _request(url, method, path):
    host, port = url.removeprefix("http://").split(":")
    conn = http.client.HTTPConnection(host, int(port), timeout=10)
    conn.request(method, path)
    res = conn.getresponse()
    return res.status, res.read()


def test_the_server_answers_get_only_and_says_when_nothing_changed(dashboard_run):
    with serving(dashboard_run) as url:
        status, body = _request(url, "GET", "/api/state")
        assert status == 200
        state = json.loads(body)
        assert [j["learner"] for j in state["runs"][0]["jobs"]] == ["identify"] * 2 + ["mobo"] * 2
        status, body = _request(url, "GET", f"/api/state?since={state['version']}")
        assert json.loads(body) == {"version": state["version"]}
        for method in ("POST", "PUT", "DELETE", "PATCH"):
            assert _request(url, method, "/api/state")[0] == 405
        assert _request(url, "GET", "/nope")[0] == 404
        status, js = _request(url, "GET", "/static/uPlot.iife.min.js")
        assert status == 200 and js.startswith(b"/*! https://github.com/leeoniya/uPlot")
        _, page = _request(url, "GET", "/")
        assert b"http" not in page  # every asset from this server
        status, body = _request(url, "GET", "/api/episode?run=0&learner=mobo")
        assert status == 400 and b"bad request" in body
        # a reference episode (theta0's, the perfect model's): its learner is blank
        ref = "/api/episode?run=0&learner=&seed=-1&phase=initial&episode=-1&start=0"
        status, body = _request(url, "GET", ref)
        assert status == 200 and len(json.loads(body)["x"]) > 0, body


def test_the_command_binds_to_localhost_and_refuses_a_missing_directory(tmp_path):
    assert inspect.signature(dashboard).parameters["host"].default == "127.0.0.1"
    assert inspect.signature(make_server).parameters["host"].default == "127.0.0.1"
    res = CliRunner().invoke(app, ["dashboard", str(tmp_path / "nope")])
    assert res.exit_code == 2 and "does not exist" in res.output
    (tmp_path / "f").write_text("x")
    res = CliRunner().invoke(app, ["dashboard", str(tmp_path / "f")])
    assert res.exit_code == 2 and "is a file" in res.output
    for port in ("-1", "65536"):  # a usage error, not bind()'s OverflowError
        res = CliRunner().invoke(app, ["dashboard", str(tmp_path), "--port", port])
        assert res.exit_code == 2 and "Invalid value for '--port'" in res.output, res.output


def test_a_file_is_read_once_per_change_and_a_damaged_one_is_a_message(dashboard_run, tmp_path):
    path = tmp_path / "episodes.parquet"
    shutil.copy(dashboard_run / "episodes.parquet", path)
    calls = []

    def reader(p):
        calls.append(p)
        return read_parquet(p)

    cache = FileCache()
    first = cache.read(path, reader)
    assert first.ok and cache.read(path, reader) is first and len(calls) == 1
    path.write_bytes(path.read_bytes()[:100])
    damaged = cache.read(path, reader)
    assert damaged.value is None and f"{path} cannot be read" in damaged.error
    os.remove(path)
    assert cache.read(path, reader).stamp is None and len(calls) == 2


def test_a_checkpoint_newer_than_the_records_gives_the_jobs_rows(dashboard_run, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(dashboard_run, out)
    ep = pd.read_parquet(out / "episodes.parquet")
    storage.write_parquet(out / "episodes.parquet", ep[ep.episode < 1])
    ckpt = out / "jobs" / "mobo-s1" / "checkpoint.pkl"
    storage.write_pickle(ckpt, dict(storage.read_pickle(ckpt), done=False))  # still running
    later = (out / "episodes.parquet").stat().st_mtime_ns + 10**9
    os.utime(ckpt, ns=(later, later))
    here = socket.gethostname()
    (out / RUNNING_FILE).write_text(json.dumps({"pid": os.getpid(), "host": here}))
    payload = run_payload(RunSource(out, FileCache()), 0)
    jobs = {(j["learner"], j["seed"]): j for j in payload["jobs"]}
    assert jobs["mobo", 1]["episode"] == [0, 1, 2] and jobs["mobo", 1]["live"]
    assert jobs["mobo", 0]["episode"] == [0] and not jobs["mobo", 0]["live"]
    assert payload["messages"] == []
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], **TEXT)
    for named, live in (({"pid": int(gone.stdout), "host": here}, False), (None, False)):
        if named is None:  # stopped by its end or Ctrl-C: the file is removed
            (out / RUNNING_FILE).unlink()
        else:  # killed with kill -9: the file names a process that is gone
            (out / RUNNING_FILE).write_text(json.dumps(named))
        jobs = {
            (j["learner"], j["seed"]): j
            for j in run_payload(RunSource(out, FileCache()), 0)["jobs"]
        }
        assert jobs["mobo", 1]["episode"] == [0, 1, 2] and jobs["mobo", 1]["live"] is live
    (out / RUNNING_FILE).write_text(json.dumps({"pid": 1, "host": here + "-elsewhere"}))
    assert RunSource(out, FileCache()).study_alive()  # on another host: cannot tell, running
    # a study in progress: no trajectories.parquet yet, the checkpoint's trajectories are shown
    os.remove(out / "trajectories.parquet")
    source = RunSource(out, FileCache())
    keys = run_payload(source, 0)["trajectories"]
    assert keys and {(k[0], k[1]) for k in keys} == {("mobo", 1)}
    key = dict(zip(["learner", "seed", "phase", "episode", "start"], keys[0]))
    assert len(source.trajectory(key)["x"]) == 2  # lq's two states


def _states(out) -> dict:
    return {
        (j["learner"], j["seed"]): j["state"]
        for j in run_payload(RunSource(out, FileCache()), 0)["jobs"]
    }


def test_a_job_killed_before_its_budget_reads_stopped_and_a_finished_one_recorded(
    dashboard_run, tmp_path
):
    """A study killed with ``kill -9`` before it wrote a summary: its unfinished jobs read
    "stopped", a job that ran its budget "recorded"; so after an extension of a complete run
    (its summary says complete) killed before the new budget, and after Ctrl-C."""
    out = tmp_path / "run"
    shutil.copytree(dashboard_run, out)
    ep = pd.read_parquet(out / "episodes.parquet")
    storage.write_parquet(out / "episodes.parquet", ep[(ep.learner != "mobo") | (ep.episode < 1)])
    ckpt = out / "jobs" / "mobo-s1" / "checkpoint.pkl"
    killed = storage.read_pickle(ckpt)  # at its third episode
    storage.write_pickle(ckpt, dict(killed, done=False, rows=killed["rows"][:2]))
    gone = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], **TEXT)
    where = {"pid": int(gone.stdout), "host": socket.gethostname()}
    (out / RUNNING_FILE).write_text(json.dumps(where))
    os.remove(out / "summary.json")
    states = _states(out)
    assert states["identify", 0] == states["identify", 1] == "recorded", states
    assert states["mobo", 0] == states["mobo", 1] == "stopped", states
    (out / RUNNING_FILE).unlink()  # Ctrl-C: the summary says the run is not complete
    storage.write_json(out / "summary.json", {"complete": False})
    assert _states(out) == states
    extended = tmp_path / "extended"
    shutil.copytree(dashboard_run, extended)  # complete, then --episodes 5 killed at once
    config = (extended / "config.toml").read_text()
    (extended / "config.toml").write_text(config.replace("episodes = 3\n", "episodes = 5\n"))
    assert set(_states(extended).values()) == {"stopped"}
    assert set(_states(dashboard_run).values()) == {"recorded"}


def _rows(incumbents, thetas, costs):
    return pd.DataFrame(
        {
            "episode": range(len(costs)),
            "theta": [list(t) for t in thetas],
            "incumbent": [list(i) for i in incumbents],
            "mean_stage_cost": costs,
            "J_eval_incumbent": [np.nan] * (len(costs) - 1) + [0.5],
        }
    )


def test_a_change_of_the_deployed_theta_carries_its_evidence():
    a, b = [1.0, 2.0], [1.0, 3.0]
    df = _rows([a, a, a, b], [a, b, b, b], [4.0, 2.0, 3.0, 1.0])
    (change,) = changes(df, np.array(a), ["q", "r"], df.mean_stage_cost.to_numpy())
    assert change["episode"] == 3 and change["changed"] == [["r", 2.0, 3.0]]
    assert (change["new_runs"], change["new_cost"]) == (3, 2.0)
    assert (change["old_runs"], change["old_cost"]) == (1, 4.0)
    assert change["J_eval"] == 0.5


def test_the_recorded_plant_cost_is_preferred_to_the_mean_stage_cost():
    df = _rows([[1.0]] * 3, [[1.0]] * 3, [4.0, 2.0, 3.0])
    assert job_series(df, None, [])["cum_cost"] == [4.0, 6.0, 9.0]
    df["plant_cost"], df["excess_cost"] = [1.0, 1.0, 2.0], [0.0, 0.5, 0.5]
    series = job_series(df, None, [])
    assert series["cum_cost"] == [1.0, 2.0, 4.0] and series["cum_excess"] == [0.0, 0.5, 1.0]
    assert series["refused"] == []
    df["refused"] = ["", "over the budget", ""]
    assert job_series(df, None, [])["refused"] == [[1, "over the budget"]]


def test_a_directory_without_a_run_or_with_a_damaged_reference_is_a_message(
    dashboard_run, tmp_path
):
    empty = tmp_path / "empty"
    empty.mkdir()
    payload = run_payload(RunSource(empty, FileCache()), 0)
    assert payload["jobs"] == [] and "does not hold a run yet" in payload["messages"][0]
    out = tmp_path / "run"
    shutil.copytree(dashboard_run, out)
    (out / "reference.pkl").write_bytes(b"not a pickle")
    payload = run_payload(RunSource(out, FileCache()), 0)
    assert any("reference.pkl cannot be read" in m for m in payload["messages"])
    assert len(payload["jobs"]) == 4 and payload["J_star"] is None


def test_the_command_serves_on_localhost_until_interrupted(dashboard_run):
    proc = subprocess.Popen(
        [sys.executable, "-m", "mpcmobo.cli", "dashboard", str(dashboard_run), "--port", "0"],
        stdout=subprocess.PIPE,
        text=True,
    )
    try:
        line = ""
        while "http://" not in line:
            line = proc.stdout.readline()
            assert line, "the command ended without serving"
        url = line.split()[3].rstrip("/")
        assert url.startswith("http://127.0.0.1:")
        status, body = _request(url, "GET", "/api/state")
        assert status == 200 and json.loads(body)["runs"][0]["kind"] == "run"
    finally:
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=120) == 0  # a fresh venv writes its bytecode on the way out


def test_several_runs_side_by_side(dashboard_run, tmp_path):
    other = tmp_path / "other"
    shutil.copytree(dashboard_run, other)
    with serving(dashboard_run, other) as url:
        _, body = _request(url, "GET", "/api/state")
    runs = json.loads(body)["runs"]
    assert [(r["index"], r["name"]) for r in runs] == [(0, dashboard_run.name), (1, "other")]
    mobo = runs[1]["groups"]["mobo"]
    assert mobo["seeds"] == 2 and len(mobo["cost"]["median"]) == 3
    costs = [j["cost"] for j in runs[1]["jobs"] if j["learner"] == "mobo"]
    assert mobo["cost"]["min"] == [min(c) for c in zip(*costs)]


def test_a_told_log_is_said_to_be_learned_from_only_while_the_tuners_process_runs(tmp_path):
    """``status.json`` says a told log is being learned from (written at the tell); the page
    says so only while the tuner's process (``mpcmobo serve``) runs, and, once it is gone,
    what ``mpcmobo status`` says (no process learns from it; the next command does); the
    process's end changes the page's version, so the page is built again."""
    from test_tuner_checks import episode

    from mpcmobo.dashboard.server import Dashboard
    from mpcmobo.experiment.tuner import Tuner

    tuner = Tuner("lq", "mpc-rl", tmp_path / "t", episodes=3, steps=6)
    trial = tuner.ask()
    tuner.accept(trial, *episode(tuner, trial))  # told, not learned from: as a killed serve
    alive = [True]
    board = Dashboard([tmp_path / "t"], serving=lambda path: alive[0])

    def said() -> tuple[str, str]:
        version, body = board.state()
        status = json.loads(body)["runs"][0]["tuner"]["status"]
        return version, status["recommendation"]["reason"]

    before, reason = said()
    assert "the tuner's process is learning from it" in reason
    alive[0] = False
    after, reason = said()
    assert after != before and "no process is learning from it" in reason
    assert "the next command that loads the tuner" in reason


def test_a_log_kept_by_a_process_killed_before_it_said_so_is_on_the_page(tmp_path, monkeypatch):
    """A tell or ``mpcmobo serve`` killed after it kept the log in ``accepted/`` and before it
    wrote ``status.json`` again: the page is built again and says what ``mpcmobo status``
    says (the log accepted, not learned from yet), not that the trial is to be run."""
    from test_tuner_checks import episode

    from mpcmobo.dashboard.server import Dashboard
    from mpcmobo.experiment.tuner import Tuner

    tuner = Tuner("lq", "mpc-rl", tmp_path / "t", episodes=3, steps=6)
    trial = tuner.ask()
    board = Dashboard([tmp_path / "t"], serving=lambda path: False)
    before = board.state()[0]
    with monkeypatch.context() as m:
        m.setattr(Tuner, "_write_status", lambda self: None)  # killed before it
        tuner.accept(trial, *episode(tuner, trial))
    version, body = board.state()
    status = json.loads(body)["runs"][0]["tuner"]["status"]
    reason = status["recommendation"]["reason"]
    assert version != before and status["learning"] == 0, reason
    assert "is accepted (accepted/trial-0.pkl)" in reason and "run it on the plant" not in reason


def test_the_episodes_with_an_error_are_named_on_the_page(dashboard_run, tmp_path):
    """A failed episode (its error in its record) is named in the page's messages with its
    job, episode and error, the first three of a job, then how many more."""
    out = tmp_path / "run"
    shutil.copytree(dashboard_run, out)
    ep = pd.read_parquet(out / "episodes.parquet")
    failed = (ep.learner == "mobo") & (ep.seed == 0)
    ep.loc[failed, "error"] = [f"PlantDiverged: step {k}" for k in ep.loc[failed, "episode"]]
    ep.loc[failed, "mean_stage_cost"] = np.nan
    storage.write_parquet(out / "episodes.parquet", ep)
    messages = run_payload(RunSource(out, FileCache()), 0)["messages"]
    assert "mobo seed 0, episode 0: PlantDiverged: step 0" in messages
    assert sum(m.startswith("mobo seed 0") for m in messages) == min(3, int(failed.sum())) + (
        int(failed.sum()) > 3
    )


def test_a_damaged_episodes_file_leaves_the_jobs_rows_from_their_checkpoints(
    dashboard_run, tmp_path
):
    """``episodes.parquet`` that cannot be read is named on the page, and the jobs' rows come
    from their checkpoints (intact), so the table and the curves stay."""
    out = tmp_path / "run"
    shutil.copytree(dashboard_run, out)
    (out / "episodes.parquet").write_bytes(b"not parquet")
    payload = run_payload(RunSource(out, FileCache()), 0)
    assert any("episodes.parquet cannot be read" in m for m in payload["messages"])
    jobs = {(j["learner"], j["seed"]): j for j in payload["jobs"]}
    assert len(jobs) == 4 and all(j["episode"] == [0, 1, 2] for j in jobs.values())
    assert not any(j["live"] for j in jobs.values())  # finished jobs: recorded, not running


def test_a_directory_deleted_while_the_page_is_open_is_named_so(dashboard_run, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(dashboard_run, out)
    source = RunSource(out, FileCache())
    run_payload(source, 0)
    shutil.rmtree(out)
    messages = run_payload(source, 0)["messages"]
    assert f"{out} no longer exists (moved or deleted)" in messages
