"""User systems through the command line: a user's system in a temporary file, run with every
learner and two workers, interrupted and resumed; bad factories and mismatched plants exit with
code 2, one line and no traceback; ``mpcmobo systems`` lists plug-ins.

The timeouts only keep a broken build from hanging the suite; nothing is timed."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pandas as pd
import pytest
from typer.testing import CliRunner
from user_system_source import write_user_files

import mpcmobo
from mpcmobo.cli import app
from mpcmobo.experiment import storage
from mpcmobo.learners.registry import LEARNER_SPECS

runner = CliRunner()
WALL = ["mpc_time_s", "learner_time_s", "eval_time_s"]
GUARD_S = 240  # a hang guard, not a measurement


def same_source_env() -> dict[str, str]:
    """The environment of a child Python: this test's ``mpcmobo`` first on its path, so that the
    child runs the source tree under test (not whichever copy is installed)."""
    src = str(Path(mpcmobo.__file__).parents[1])
    path = os.environ.get("PYTHONPATH")
    return dict(os.environ, PYTHONPATH=src if not path else f"{src}{os.pathsep}{path}")


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    return write_user_files(tmp_path_factory.mktemp("user"))


def run_args(spec: str, out: Path, workers: int, *extra: str) -> list[str]:
    return [
        "run",
        "--system",
        spec,
        "--learner",
        "all",
        "--episodes",
        "3",
        "--workers",
        str(workers),
        "--out",
        str(out),
        "--no-plot",
        *extra,
    ]


def records(out: Path) -> pd.DataFrame:
    df = storage.read_episodes(out).drop(columns=WALL)
    return df.sort_values(["learner", "seed", "episode"]).reset_index(drop=True)


def test_a_system_in_a_file_runs_every_learner_on_two_workers_and_resumes(files, tmp_path):
    """Acceptance: 3 episodes of each learner through the CLI with --workers 2 (the workers
    import the factory from its path), interrupted by Ctrl-C and resumed; the records equal an
    uninterrupted run's."""
    spec = f"{files}/usersys.py:make_system"
    out = tmp_path / "interrupted"
    proc = subprocess.Popen(
        [sys.executable, "-m", "mpcmobo.cli", *run_args(spec, out, 2)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env=same_source_env(),
    )
    jobs = out / "jobs"
    deadline = time.monotonic() + GUARD_S
    while proc.poll() is None and not (jobs.exists() and any(jobs.glob("*/checkpoint.pkl"))):
        assert time.monotonic() < deadline, "no checkpoint"
        time.sleep(0.05)
    os.killpg(proc.pid, signal.SIGINT)
    _, err = proc.communicate(timeout=GUARD_S)
    assert proc.returncode == 130, err
    assert "Traceback" not in err, err
    n_done = len(storage.read_episodes(out))
    assert n_done < 12, f"not interrupted before the end ({n_done} episodes): {err}"
    res = runner.invoke(app, ["run", "--resume", "--out", str(out), "--quiet", "--no-plot"])
    assert res.exit_code == 0, res.output
    ref = tmp_path / "uninterrupted"
    res = runner.invoke(app, [*run_args(spec, ref, 1), "--quiet"])
    assert res.exit_code == 0, res.output
    got, want = records(out), records(ref)
    assert len(got) == 3 * len(LEARNER_SPECS) and set(got.learner) == set(LEARNER_SPECS)
    pd.testing.assert_frame_equal(got, want)
    summary = storage.read_json(out / "summary.json")
    assert summary["system"] == "double_integrator" and summary["J_star"] is not None


@pytest.mark.parametrize(
    "spec, plant, message",
    [
        ("nope_pkg.nope:make_system", None, "cannot import module 'nope_pkg.nope'"),
        ("{d}/missing.py:make_system", None, "file not found"),
        ("{d}/raises.py:make_system", None, "RuntimeError: this file does not import"),
        ("{d}/usersys.py:make_wrong_type", None, "returned dict, expected a mpcmobo.systems"),
        ("{d}/usersys.py:make_broadcast", None, "returns shape (1, 1), expected (2 states, 1)"),
        (
            "{d}/usersys.py:make_system",
            "{d}/userplant.py:make_env_3",
            "observation space has shape (3,), but the model 'double_integrator' has 2 states",
        ),
        ("lq", "{d}/userplant.py:nope", "has no attribute 'nope'"),
    ],
)
def test_bad_factories_and_plants_exit_2_with_one_line(files, tmp_path, spec, plant, message):
    spec = spec.format(d=files)
    args = [
        "run",
        "--system",
        spec,
        "--episodes",
        "1",
        "--workers",
        "1",
        "--out",
        str(tmp_path / "o"),
        "--quiet",
    ]
    if plant is not None:
        cfg = tmp_path / "c.toml"
        cfg.write_text(f'[system]\nplant = "{plant.format(d=files)}"\n')
        args += ["--config", str(cfg)]
    res = runner.invoke(app, args)
    assert res.exit_code == 2, res.output
    assert "Traceback" not in res.output
    assert message in " ".join(res.output.split())
    assert len(res.output.strip().splitlines()) == 1, res.output
    assert not (tmp_path / "o" / "config.toml").exists()


def test_systems_lists_plugins_and_says_how_to_add_one(files, tmp_path, monkeypatch):
    dist = tmp_path / "userplug-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: userplug\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[mpcmobo.systems]\ndi = usersys:make_system\n")
    monkeypatch.syspath_prepend(str(files))
    monkeypatch.syspath_prepend(str(tmp_path))
    from rich.console import Console

    import mpcmobo.cli as cli

    monkeypatch.setattr(cli, "console", Console(width=250))  # the table unwrapped
    res = runner.invoke(app, ["systems"])
    assert res.exit_code == 0, res.output
    lines = {line.split()[1]: line for line in res.output.splitlines() if line.startswith("│")}
    assert "built-in" in lines["cstr"] and "plug-in usersys:make_system (userplug)" in lines["di"]
    assert "pos, vel" in lines["di"] and "force" in lines["di"]
    # one description line per system, after the table: its kind and its description
    notes = [line for line in res.output.splitlines() if line.startswith("di (")]
    assert len(notes) == 1 and notes[0].startswith("di (discrete-time, 1 path constraint): ")
    assert "--system path/to/file.py:make_system" in res.output
    assert '"mpcmobo.systems"' in res.output


@pytest.mark.parametrize(
    "edit, named",
    [
        (("imperfect=(0.6,)", "imperfect=(0.7,)"), "nominal_params"),
        (("x[0] + 0.5 * x[1] - 1.5", "x[0] + 0.5 * x[1] - 1.4"), "its equations"),
        (("Q=np.array([1.0, 0.2])", "Q=np.array([1.0, 0.3])"), "Q, theta0"),
    ],
)
def test_a_resume_refuses_a_system_whose_file_changed(tmp_path, edit, named):
    """The system's file edited between a run and its resume (a model parameter, its
    constraint's expression, or a weight of the stage cost): the resume and ``evaluate`` are
    refused naming what changed (exit 1, as a resume with a shorter budget), and write
    nothing; the file put back, the run resumes."""
    (tmp_path / "user").mkdir()
    d = write_user_files(tmp_path / "user")
    spec = f"{d}/usersys.py:make_system"
    out = tmp_path / "run"
    args = ["run", "--system", spec, "--learner", "identify", "--episodes", "1", "--quiet"]
    res = runner.invoke(app, [*args, "--out", str(out), "--no-plot"])
    assert res.exit_code == 0, res.output
    source = (d / "usersys.py").read_text()
    assert edit[0] in source
    (d / "usersys.py").write_text(source.replace(edit[0], edit[1]))
    before = sorted((p.name, p.stat().st_mtime_ns) for p in out.rglob("*") if p.is_file())
    resume = [sys.executable, "-m", "mpcmobo.cli", "run", "--resume", "--out", str(out)]
    resume += ["--episodes", "2", "--quiet", "--no-plot"]  # a new process imports the file anew
    res = subprocess.run(resume, capture_output=True, text=True, env=same_source_env())
    assert res.returncode == 1, res.stdout + res.stderr  # as the other refusals of a resume
    said = " ".join((res.stdout + res.stderr).split())
    assert "not the one the run" in said and named in said and "Traceback" not in said
    evaluate = [sys.executable, "-m", "mpcmobo.cli", "evaluate", str(out)]
    res = subprocess.run(evaluate, capture_output=True, text=True, env=same_source_env())
    said = " ".join((res.stdout + res.stderr).split())
    assert res.returncode == 1 and "not the one the run" in said and named in said, said
    assert sorted((p.name, p.stat().st_mtime_ns) for p in out.rglob("*") if p.is_file()) == before
    (d / "usersys.py").write_text(source)
    res = subprocess.run(resume, capture_output=True, text=True, env=same_source_env())
    assert res.returncode == 0, res.stdout + res.stderr


def test_a_tuner_refuses_its_pending_trial_once_its_systems_file_changed(tmp_path):
    """A tuner's pending trial is handed out without loading the tuner; once its system's file
    is newer than its reference and the system differs, ``ask`` loads it and is refused,
    before the plant runs the trial, naming the tuner and the file."""
    (tmp_path / "user").mkdir()
    d = write_user_files(tmp_path / "user")
    spec = f"{d}/usersys.py:make_system"
    out = tmp_path / "tuner"
    cmd = [sys.executable, "-m", "mpcmobo.cli", "ask", str(out)]
    env = same_source_env()
    res = subprocess.run(
        [*cmd, "--system", spec, "--episodes", "3"], capture_output=True, text=True, env=env
    )
    assert res.returncode == 0, res.stderr
    source = (d / "usersys.py").read_text()
    (d / "usersys.py").write_text(source.replace("imperfect=(0.6,)", "imperfect=(0.7,)"))
    res = subprocess.run(cmd, capture_output=True, text=True, env=env)
    said = " ".join((res.stdout + res.stderr).split())
    assert res.returncode == 1, said
    assert f"the tuner in {out} (its system from {spec})" in said and "nominal_params" in said
    (d / "usersys.py").write_text(source)  # as it was: the pending trial again
    res = subprocess.run(cmd, capture_output=True, text=True, env=env)
    assert res.returncode == 0 and '"id": 0' in res.stdout, res.stdout + res.stderr
