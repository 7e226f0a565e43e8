"""Wall time of the tuner's commands on a tuner of 50 told trials: status, ask, tell.

``--out DIR`` holds the tuner: made there the first time (``--trials`` trials of ``--learner``
on ``--system``, told through the Python API from simulated episodes, with a budget of
two more), reused after. Each repeat works on a copy of it and times the
command line as subprocesses (``python -m mpcmobo.cli``): ``status DIR``, ``status DIR
--json``, ``ask`` (a new trial: the tuner loaded, the learner's proposal), ``ask`` again (the
pending trial, as the first ask wrote it), ``tell`` of a missing file and of a malformed one
(a CSV without the system's columns), ``tell`` of the trial's simulated log (a CSV; the
episode runs between the timings, in this process; the tell then prepares the next trial),
and ``ask`` after it (the trial the tell prepared). Then the same with the tuner's process
serving the copy (``mpcmobo serve``, started before the round and not timed): ``tell`` (answered
once the log is checked), ``ask`` right after it (it waits for the learning and the next
proposal, and shows them), ``ask`` once the trial is prepared, ``tell`` of a malformed file. The
baseline, measured in the same run: the interpreter's start (``python -c pass``). Printed: a
markdown table of the median and max seconds per command against its target (status 1 s, ask
and tell 2 s, a bad log 1 s; an ``ask`` that waits for the learning has none).

    .venv/bin/python benchmarks/tuner_latency.py --out /tmp/tuner50            # lq, 5 repeats
    .venv/bin/python benchmarks/tuner_latency.py --out /tmp/tuner50 --repeats 3 --system cstr
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
TARGETS = {
    "python -c pass": None,
    "status": 1.0,
    "status --json": 1.0,
    "ask (new trial)": 2.0,
    "ask (pending)": 2.0,
    "tell": 2.0,
    "ask (prepared by the tell)": 2.0,
    "tell (missing file)": 1.0,
    "tell (malformed file)": 1.0,
    "served: tell": 2.0,
    "served: ask right after the tell (waits for the learning)": None,
    "served: ask (prepared)": 2.0,
    "served: tell (malformed file)": 1.0,
}


def _episode(tuner, trial, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """The trial on the simulated plant: its policy plus its noise, clipped."""
    from mpcmobo.systems.plant import SystemPlant

    plant = SystemPlant(tuner.system)
    trial.restart()
    x, _ = plant.reset(seed=seed, options={"x0": trial.x0})
    states, inputs = [x], []
    for k in range(trial.steps):
        u = np.clip(trial.policy(x) + trial.noise[k], tuner.system.u_lb, tuner.system.u_ub)
        x, *_ = plant.step(u)
        states.append(x)
        inputs.append(u)
    return np.array(states), np.array(inputs)


def build(out: Path, system: str, learner: str, trials: int, budget: int) -> None:
    """A tuner of ``trials`` told trials in ``out`` (kept if it has them already)."""
    from mpcmobo.experiment.tuner import Tuner, TunerError

    if (out / "config.toml").exists():
        from mpcmobo.experiment.rundir import RunDirectory

        saved = RunDirectory(out).saved_settings().episodes
        tuner = Tuner.load(out, episodes=max(saved, trials + 2))
    else:
        tuner = Tuner(system, learner, out, episodes=budget)
    t0 = time.perf_counter()
    while tuner.episodes < trials:
        trial = tuner.ask()
        X, U = _episode(tuner, trial, trial.id)
        try:
            tuner.tell(trial, X, U)
        except TunerError:  # a log the checks quarantine: told all the same
            tuner.tell(trial, X, U, force=True)
        print(f"made trial {trial.id} ({time.perf_counter() - t0:.0f} s)", flush=True)


def _timed(cmd: list[str], expect: int) -> float:
    """The wall time of ``cmd``; its exit code must be ``expect``."""
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True)
    took = time.perf_counter() - t0
    if proc.returncode != expect:
        raise SystemExit(
            f"{' '.join(cmd)}: exit code {proc.returncode}, not {expect}\n{proc.stderr[-2000:]}"
        )
    return took


def repeat(base: Path, work: Path, seed: int) -> dict[str, float]:
    """One round of the commands on a copy of the tuner in ``base``."""
    from mpcmobo.experiment.tuner import Tuner, write_log

    d = work / f"tuner-{seed}"
    shutil.rmtree(d, ignore_errors=True)
    shutil.copytree(base, d)
    cli = [sys.executable, "-m", "mpcmobo.cli"]
    t = {"python -c pass": _timed([sys.executable, "-c", "pass"], 0)}
    t["status"] = _timed([*cli, "status", str(d)], 0)
    t["status --json"] = _timed([*cli, "status", str(d), "--json"], 0)
    t["ask (new trial)"] = _timed([*cli, "ask", str(d)], 0)
    t["ask (pending)"] = _timed([*cli, "ask", str(d)], 0)
    tuner = Tuner.load(d)
    trial = tuner.ask()
    log = write_log(work / f"trial-{seed}.csv", *_episode(tuner, trial, seed), tuner.system)
    bad = work / "malformed.csv"
    bad.write_text("a,b\n1,2\n")
    t["tell (missing file)"] = _timed(
        [*cli, "tell", str(d), str(trial.id), str(work / "no.csv")], 2
    )
    t["tell (malformed file)"] = _timed([*cli, "tell", str(d), str(trial.id), str(bad)], 2)
    t["tell"] = _timed([*cli, "tell", str(d), str(trial.id), str(log), "--force"], 0)
    t["ask (prepared by the tell)"] = _timed([*cli, "ask", str(d)], 0)
    shutil.rmtree(d, ignore_errors=True)
    shutil.copytree(base, d)
    t.update(_served(d, work, seed))
    shutil.rmtree(d, ignore_errors=True)
    return t


def _served(d: Path, work: Path, seed: int) -> dict[str, float]:
    """The commands with ``mpcmobo serve d`` running (its start not timed)."""
    from mpcmobo.cli.resident import request
    from mpcmobo.experiment.tuner import Tuner, write_log

    cli = [sys.executable, "-m", "mpcmobo.cli"]
    proc = subprocess.Popen([*cli, "serve", str(d)], stdout=subprocess.DEVNULL)
    t: dict[str, float] = {}
    try:
        while not request(d, "ping")[0]:
            if proc.poll() is not None:
                raise SystemExit(f"mpcmobo serve {d} exited with {proc.returncode}")
            time.sleep(0.2)
        tid = int(request(d, "ask")[1]["id"])  # the pending trial, as the process prepared it
        tuner = Tuner.load(d)
        trial = tuner.ask()
        log = write_log(work / f"served-{seed}.csv", *_episode(tuner, trial, seed), tuner.system)
        t["served: tell (malformed file)"] = _timed(
            [*cli, "tell", str(d), str(tid), str(work / "malformed.csv")], 2
        )
        t["served: tell"] = _timed([*cli, "tell", str(d), str(tid), str(log), "--force"], 0)
        t["served: ask right after the tell (waits for the learning)"] = _timed(
            [*cli, "ask", str(d)], 0
        )
        t["served: ask (prepared)"] = _timed([*cli, "ask", str(d)], 0)
    finally:
        proc.send_signal(signal.SIGTERM)  # SIGINT may be ignored in a background job
        proc.wait(timeout=120)
    return t


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=None, help="the tuner's directory (reused)")
    ap.add_argument("--system", default="lq")
    ap.add_argument("--learner", default="mobo")
    ap.add_argument("--trials", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()
    os.environ["PYTHONPATH"] = os.pathsep.join(
        [str(ROOT / "src"), *filter(None, [os.environ.get("PYTHONPATH")])]
    )
    with tempfile.TemporaryDirectory() as tmp:
        out = args.out or Path(tmp) / "tuner"
        build(out, args.system, args.learner, args.trials, args.trials + 2)
        times: dict[str, list[float]] = {k: [] for k in TARGETS}
        for r in range(args.repeats):
            for k, v in repeat(out, Path(tmp), r).items():
                times[k].append(v)
            print(f"repeat {r + 1}/{args.repeats} done", flush=True)
    print(
        f"\n{args.learner} tuner of {args.trials} told trials on {args.system}, "
        f"{args.repeats} repeats, {os.cpu_count()} cores\n"
    )
    print("| command | median s | max s | target s | met |")
    print("|---|---:|---:|---:|---|")
    for k, target in TARGETS.items():
        med, worst = statistics.median(times[k]), max(times[k])
        met = "" if target is None else ("yes" if worst <= target else "no")
        goal = "-" if target is None else f"{target:g}"
        print(f"| {k} | {med:.2f} | {worst:.2f} | {goal} | {met} |")


if __name__ == "__main__":
    main()
