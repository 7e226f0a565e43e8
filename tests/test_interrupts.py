"""Interrupts and orphaned workers: SIGINT / SIGTERM stop a run with exit code 130 /
143, records that are a prefix of the uninterrupted run's and no solver failure; ``--resume``
then gives the uninterrupted records; workers never outlive their study.

The timeouts below only keep a broken build from hanging the suite; nothing is timed."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
import tomllib
from pathlib import Path

import pandas as pd
import pytest

import mpcmobo
from mpcmobo.experiment import storage
from mpcmobo.experiment.interrupts import Interrupted
from mpcmobo.experiment.settings import load_settings
from mpcmobo.experiment.study import run_study

WALL = ["mpc_time_s", "learner_time_s", "eval_time_s"]
EPISODES, STEPS = 25, 30
CONFIG = f"""
system = {{ name = "lq" }}
learners = ["mpc-rl"]
episodes = {EPISODES}
steps = {STEPS}
evaluation = {{ n_starts = 2 }}
"""
GUARD_S = 120  # a hang guard, not a measurement


def same_source_env() -> dict[str, str]:
    """The environment of a child Python: this test's ``mpcmobo`` first on its path, so that the
    child runs the source tree under test (not whichever copy is installed)."""
    src = str(Path(mpcmobo.__file__).parents[1])
    path = os.environ.get("PYTHONPATH")
    return dict(os.environ, PYTHONPATH=src if not path else f"{src}{os.pathsep}{path}")


def settings(seeds=(0,), workers=1):
    return load_settings(None, **tomllib.loads(CONFIG), seeds=list(seeds), workers=workers)


@pytest.fixture(scope="module")
def config(tmp_path_factory) -> str:
    path = tmp_path_factory.mktemp("config") / "run.toml"
    path.write_text(CONFIG)
    return str(path)


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    """The uninterrupted run (two seeds, so that it serves the worker tests too)."""
    out = tmp_path_factory.mktemp("ref") / "run"
    run_study(settings(seeds=(0, 1)), out)
    return storage.read_episodes(out).drop(columns=WALL)


def rows(out: Path, seed: int | None = None) -> pd.DataFrame:
    df = storage.read_episodes(out).drop(columns=WALL)
    return df if seed is None else df[df.seed == seed].reset_index(drop=True)


def assert_prefix(df: pd.DataFrame, ref: pd.DataFrame) -> None:
    """``df`` (one job) equals the first len(df) rows of the same job in ``ref``."""
    assert len(df) > 0
    for seed, part in df.groupby("seed"):
        part = part.reset_index(drop=True)
        full = ref[ref.seed == seed].reset_index(drop=True).iloc[: len(part)]
        pd.testing.assert_frame_equal(part, full)


def episodes_done(out: Path, seed: int = 0) -> int:
    try:
        ckpt = storage.load_checkpoint(out, "mpc-rl", seed)
    except Exception:  # noqa: BLE001 - being replaced
        return 0
    return 0 if ckpt is None else len(ckpt["rows"])


def wait_until(cond, what: str, timeout: float = GUARD_S) -> None:
    deadline = time.monotonic() + timeout
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"gave up waiting for {what}")
        time.sleep(0.05)


def cli(config: str, args: list[str]) -> subprocess.Popen:
    """``mpcmobo run --config CONFIG ...`` in its own session (a Ctrl-C reaches its whole
    process group)."""
    return subprocess.Popen(
        [sys.executable, "-m", "mpcmobo.cli", "run", "--config", config, "--no-plot", *args],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        env=same_source_env(),
    )


def children(pid: int) -> set[int]:
    """The worker processes (spawned by multiprocessing) whose parent is ``pid``."""
    out = set()
    for entry in Path("/proc").iterdir():
        if entry.name.isdigit():
            try:
                stat = (entry / "stat").read_text()
                cmdline = (entry / "cmdline").read_bytes()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid and b"spawn_main" in cmdline:
                out.add(int(entry.name))
    return out


def alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except OSError:
        return False
    return state != "Z"


def resume(out: Path, workers: int | None = None) -> dict:
    """``mpcmobo run --resume --out DIR [--workers N]``, in this process (the CLI is tested
    above; here it would only add its start-up time)."""
    changed = None if workers is None else load_settings(out / "config.toml", workers=workers)
    return run_study(changed, out, resume=True)


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_signal_stops_a_single_process_run_and_resume_completes_it(
    reference, config, tmp_path, sig, code
):
    out = tmp_path / "run"
    proc = cli(config, ["--workers", "1", "--out", str(out)])
    wait_until(lambda: episodes_done(out) >= 2 or proc.poll() is not None, "two episodes")
    os.killpg(proc.pid, sig)
    _, err = proc.communicate(timeout=GUARD_S)
    assert proc.returncode == code, err
    assert "--resume --out" in err and "Traceback" not in err
    interrupted = rows(out)
    assert len(interrupted) < EPISODES
    assert_prefix(interrupted, reference)
    assert (interrupted.solver_failures == 0).all()
    assert resume(out)["complete"] is True
    pd.testing.assert_frame_equal(rows(out), rows_of(reference, 0))


def rows_of(ref: pd.DataFrame, seed: int) -> pd.DataFrame:
    return ref[ref.seed == seed].reset_index(drop=True)


def test_repeated_interrupts_during_solves_are_never_solver_failures(reference, tmp_path):
    """SIGINT every few milliseconds, so that many land inside IPOPT: the run stops with
    Interrupted (not carried on with failed solves) and every recorded episode is the
    uninterrupted one."""
    out = tmp_path / "run"
    stop = threading.Event()

    def kick() -> None:
        wait_until(lambda: episodes_done(out) >= 2 or stop.is_set(), "two episodes")
        while not stop.is_set():
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.003)

    previous = signal.signal(signal.SIGINT, lambda *a: None)  # after the study: nothing
    kicker = threading.Thread(target=kick, daemon=True)
    kicker.start()
    try:
        with pytest.raises(Interrupted) as info:
            run_study(settings(), out)
    finally:
        stop.set()
        kicker.join()
        signal.signal(signal.SIGINT, previous)
    assert info.value.exit_code == 130
    interrupted = rows(out)
    assert 2 <= len(interrupted) < EPISODES
    assert_prefix(interrupted, reference)
    assert (interrupted.solver_failures == 0).all()
    assert resume(out)["complete"] is True
    pd.testing.assert_frame_equal(rows(out), rows_of(reference, 0))


def test_ctrl_c_stops_the_workers_too(reference, config, tmp_path):
    out = tmp_path / "run"
    proc = cli(config, ["--seeds", "0", "1", "--workers", "2", "--out", str(out)])
    wait_until(
        lambda: min(episodes_done(out, 0), episodes_done(out, 1)) >= 2 or proc.poll() is not None,
        "two episodes of each job",
    )
    workers = children(proc.pid)
    os.killpg(proc.pid, signal.SIGINT)  # what a Ctrl-C in a terminal does
    _, err = proc.communicate(timeout=GUARD_S)
    assert proc.returncode == 130, err
    assert "--resume --out" in err and "Traceback" not in err
    assert workers and not any(alive(p) for p in workers)
    interrupted = rows(out)
    assert len(interrupted) < 2 * EPISODES  # the workers did not run their jobs to the end
    assert_prefix(interrupted, reference)
    assert resume(out)["complete"] is True  # the records do not depend on the workers
    pd.testing.assert_frame_equal(rows(out), reference)


def test_sigterm_stops_a_ray_study_and_its_cluster(reference, tmp_path):
    """With backend = "ray" the study's SIGTERM handler survives ray.init: SIGTERM to the
    study's process stops it with 143 and the resume hint, and the records are a prefix of the
    uninterrupted run's."""
    pytest.importorskip("ray")
    config = tmp_path / "ray.toml"
    config.write_text(CONFIG + 'backend = "ray"\n')
    out = tmp_path / "run"
    proc = cli(str(config), ["--seeds", "0", "1", "--workers", "2", "--out", str(out)])
    wait_until(lambda: episodes_done(out) >= 2 or proc.poll() is not None, "two episodes")
    os.kill(proc.pid, signal.SIGTERM)
    _, err = proc.communicate(timeout=GUARD_S)
    assert proc.returncode == 143, err
    assert "--resume --out" in err and "Traceback" not in err and "SIGTERM received" not in err
    for seed in (0, 1):
        if episodes_done(out, seed):
            assert_prefix(rows(out, seed), reference)


def test_busy_workers_exit_when_the_study_is_killed(reference, config, tmp_path):
    out = tmp_path / "run"
    proc = cli(config, ["--seeds", "0", "1", "--workers", "2", "--out", str(out), "-q"])
    wait_until(
        lambda: min(episodes_done(out, 0), episodes_done(out, 1)) >= 1 or proc.poll() is not None,
        "an episode of each job",
    )
    workers = children(proc.pid)
    assert workers
    os.kill(proc.pid, signal.SIGKILL)
    proc.communicate(timeout=GUARD_S)
    wait_until(lambda: not any(alive(p) for p in workers), "the orphaned workers to exit", 60)
    for seed in (0, 1):  # their last checkpoints are intact: a prefix of the uninterrupted run
        ckpt = storage.load_checkpoint(out, "mpc-rl", seed)
        part = pd.DataFrame(ckpt["rows"]).drop(columns=WALL)
        assert_prefix(part, reference)


PARENT = """
import sys, time, multiprocessing as mp, os
from concurrent.futures import ProcessPoolExecutor
from mpcmobo.experiment import interrupts
if __name__ == "__main__":
    ctx = mp.get_context("spawn")
    pool = ProcessPoolExecutor(2, mp_context=ctx, initializer=interrupts.init_worker,
                               initargs=(os.getpid(), None))
    print(list(pool.map(abs, range(2))), flush=True)  # the workers are up
    print(*[p.pid for p in pool._processes.values()], flush=True)
    time.sleep(600)
"""


def test_idle_workers_exit_when_the_study_is_killed(tmp_path):
    script = tmp_path / "parent.py"
    script.write_text(PARENT)
    proc = subprocess.Popen(
        [sys.executable, str(script)], stdout=subprocess.PIPE, text=True, env=same_source_env()
    )
    proc.stdout.readline()
    workers = {int(p) for p in proc.stdout.readline().split()}
    assert workers and all(alive(p) for p in workers)
    os.kill(proc.pid, signal.SIGKILL)
    proc.wait(timeout=GUARD_S)
    wait_until(lambda: not any(alive(p) for p in workers), "the idle workers to exit", 60)


def test_an_interrupt_inside_a_solve_ends_it_normally():
    """SIGINTs land inside IPOPT: each solve still completes as usual (no failed status), and
    Interrupted is raised once it has returned."""
    import numpy as np

    from mpcmobo.experiment import interrupts
    from mpcmobo.mpc import ParametricMPC
    from mpcmobo.systems import get_system

    system = get_system("cstr")
    mpc = ParametricMPC(system, model="imperfect")
    statuses = []
    raw = mpc.solve

    in_solve = threading.Event()

    def recorded(*args, **kwargs):
        in_solve.set()
        try:
            sol = raw(*args, **kwargs)
        finally:
            in_solve.clear()
        statuses.append(sol.status)
        return sol

    mpc.solve = recorded
    interrupts.guard_solves(mpc)
    rng = np.random.default_rng(0)
    starts = [system.sample_initial_state(rng) for _ in range(5)]
    stop = threading.Event()

    def kick() -> None:  # only while a solve runs
        while not stop.is_set():
            if in_solve.is_set():
                os.kill(os.getpid(), signal.SIGINT)
            time.sleep(0.0005)

    previous = signal.signal(signal.SIGINT, lambda *a: None)
    kicker = threading.Thread(target=kick, daemon=True)
    try:
        with pytest.raises(Interrupted), interrupts.catching():
            kicker.start()
            for _ in range(200):
                for x in starts:
                    mpc.solve(x, mpc.theta0)
    finally:
        stop.set()
        if kicker.is_alive():
            kicker.join()
        signal.signal(signal.SIGINT, previous)
    assert statuses  # the interrupted solve returned normally, then Interrupted was raised
    assert all(s == statuses[0] for s in statuses) and "Exception" not in statuses[0], statuses


def test_a_signal_swallowed_during_the_reference_stops_the_run(tmp_path, monkeypatch):
    """A SIGINT that lands in a solve the study does not guard (a library's own, which swallows
    it: the solve fails) leaves only the flag set: the run stops once the reference is
    computed, before that reference is kept, as a Ctrl-C elsewhere stops it (exit 130)."""
    from mpcmobo.experiment import interrupts, study

    computed = study.compute_reference

    def swallowed(settings):
        reference = computed(settings)
        interrupts.request_stop(signal.SIGINT)  # as _handler leaves it when CasADi swallows
        return reference

    monkeypatch.setattr(study, "compute_reference", swallowed)
    settings = load_settings(None, **tomllib.loads(CONFIG), workers=1)
    with pytest.raises(Interrupted) as err:
        run_study(settings, tmp_path / "run")
    assert err.value.exit_code == 130
    assert not (tmp_path / "run" / "reference.pkl").exists()
    assert not list((tmp_path / "run").glob("jobs/*/checkpoint.pkl"))


def test_a_zombie_process_is_not_alive():
    """A process that ended and was not reaped yet (a killed study whose parent has not waited
    for it) is gone for the liveness checks: a resume, a worker's watchdog, the dashboard."""
    from mpcmobo.experiment.interrupts import process_alive

    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    assert process_alive(proc.pid)
    os.kill(proc.pid, signal.SIGKILL)
    deadline = time.monotonic() + 10
    while Path(f"/proc/{proc.pid}/stat").read_text().rpartition(")")[2].split()[0] != "Z":
        assert time.monotonic() < deadline, "the child never became a zombie"
        time.sleep(0.05)
    try:
        assert not process_alive(proc.pid)
    finally:
        proc.wait()
    assert not process_alive(proc.pid)
