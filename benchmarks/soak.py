"""Kill-and-resume soak: ``kill -9`` of ``mpcmobo run`` at random moments, then ``--resume``.

Runs the study once without interruption (the reference), then ``--kills`` times: starts the
same study in a new directory and kills its main process with SIGKILL at a random moment of its
progress: once the jobs have checkpointed k episodes in total (k drawn uniformly from 0 to the
total budget - 1, or "-1": during the computation of J*), plus a delay drawn uniformly from 0 to
``--max-delay`` seconds (inside an episode, a checkpoint write or an evaluation). It checks that
the worker processes exit by themselves, resumes the run with ``mpcmobo run --resume`` and
compares ``episodes.parquet`` (wall-time columns aside) and ``trajectories.parquet`` with the
reference's. Prints a markdown table and writes ``OUT/soak.json``.

    .venv/bin/python benchmarks/soak.py --out runs/soak                    # 10 kills, lq
    .venv/bin/python benchmarks/soak.py --system cstr --episodes 6 --steps 20 --out runs/soak-cstr
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pandas as pd

from mpcmobo.experiment import storage

WALL = ["mpc_time_s", "learner_time_s", "eval_time_s"]
ORPHAN_WAIT_S = 30.0  # how long the orphaned workers are given to exit


def config_text(args: argparse.Namespace) -> str:
    learners = ", ".join(f'"{n}"' for n in args.learners)
    seeds = ", ".join(str(s) for s in args.seeds)
    return (
        f'system = {{ name = "{args.system}" }}\nlearners = [{learners}]\n'
        f"episodes = {args.episodes}\nsteps = {args.steps}\nseeds = [{seeds}]\n"
        f"workers = {args.workers}\nevaluation = {{ n_starts = {args.n_starts} }}\n"
        "learner_options = { bo = { n_init = 3 } }\n"
    )


def start(config: Path, out: Path) -> subprocess.Popen:
    cmd = [sys.executable, "-m", "mpcmobo.cli", "run", "--config", str(config), "--out",
           str(out), "-q", "--no-plot"]  # fmt: skip
    return subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)


def workers_of(pid: int) -> set[int]:
    """The multiprocessing children of ``pid`` (Linux /proc)."""
    out = set()
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        if ppid == pid and b"spawn_main" in cmdline:
            out.add(int(entry.name))
    return out


def alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def same_records(a: Path, b: Path) -> bool:
    try:
        ea = storage.read_episodes(a).drop(columns=WALL)
        eb = storage.read_episodes(b).drop(columns=WALL)
        pd.testing.assert_frame_equal(ea, eb)
        pd.testing.assert_frame_equal(storage.read_trajectories(a), storage.read_trajectories(b))
    except (AssertionError, OSError, ValueError) as err:
        print(f"  differs: {str(err).splitlines()[0]}", flush=True)
        return False
    return True


def episodes_done(out: Path) -> int:
    n = 0
    for ck in out.glob("jobs/*/checkpoint.pkl"):
        try:
            n += len(storage.read_pickle(ck)["rows"])
        except Exception:  # noqa: BLE001 - reported as unreadable by the resume
            pass
    return n


def wait_for_config(proc: subprocess.Popen, out: Path) -> float:
    """Seconds until the run's config.toml exists (the run directory is set up)."""
    t0 = time.monotonic()
    while not (out / "config.toml").exists() and proc.poll() is None:
        time.sleep(0.01)
    return time.monotonic() - t0


def trial(config: Path, out: Path, k: int, delay: float) -> dict:
    """Start the study; kill it ``delay`` seconds after it has checkpointed ``k`` episodes
    (k = -1: after its config.toml exists); resume it."""
    proc = start(config, out)
    seen: set[int] = set()
    wait_for_config(proc, out)
    while k >= 0 and episodes_done(out) < k + 1 and proc.poll() is None:
        seen |= workers_of(proc.pid)
        time.sleep(0.02)
    deadline = time.monotonic() + delay
    while time.monotonic() < deadline and proc.poll() is None:
        seen |= workers_of(proc.pid)
        time.sleep(0.02)
    finished_first = proc.poll() is not None
    proc.kill()
    proc.wait()
    done_at_kill = episodes_done(out)
    t0 = time.monotonic()
    while any(alive(p) for p in seen) and time.monotonic() - t0 < ORPHAN_WAIT_S:
        time.sleep(0.05)
    orphans = sorted(p for p in seen if alive(p))
    orphan_exit_s = time.monotonic() - t0
    res = subprocess.run(
        [
            sys.executable,
            "-m",
            "mpcmobo.cli",
            "run",
            "--resume",
            "--out",
            str(out),
            "-q",
            "--no-plot",
        ],  # fmt: skip
        capture_output=True,
        text=True,
    )
    return {
        "after_episodes": k,
        "delay_s": round(delay, 2),
        "finished_before_kill": finished_first,
        "episodes_at_kill": done_at_kill,
        "workers_seen": len(seen),
        "workers_left_after_wait": len(orphans),
        "workers_exit_s": round(orphan_exit_s, 2),
        "resume_exit_code": res.returncode,
        "resume_error": res.stderr.strip()[-300:] if res.returncode else "",
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--system", default="lq")
    p.add_argument("--learners", nargs="+", default=["mpc-rl", "bo"])
    p.add_argument("--episodes", type=int, default=20)
    p.add_argument("--steps", type=int, default=30)
    p.add_argument("--seeds", type=int, nargs="+", default=[0])
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--n-starts", type=int, default=2)
    p.add_argument("--kills", type=int, default=10)
    p.add_argument("--seed", type=int, default=0, help="seed of the kill moments")
    p.add_argument("--max-delay", type=float, default=1.0, help="seconds after the k-th episode")
    p.add_argument("--out", type=Path, default=Path("runs/soak"))
    args = p.parse_args()

    if args.out.exists():
        shutil.rmtree(args.out)
    args.out.mkdir(parents=True)
    config = args.out / "soak.toml"
    config.write_text(config_text(args))
    ref = args.out / "reference"
    proc = start(config, ref)
    startup = wait_for_config(proc, ref)
    t0 = time.monotonic()
    _, err = proc.communicate()
    wall = time.monotonic() - t0  # from config.toml to the end
    if proc.returncode != 0:
        raise SystemExit(f"the reference run failed ({proc.returncode}): {err}")
    print(f"reference run: start-up {startup:.1f} s, then {wall:.1f} s ({args.system}, {args.learners}, {args.episodes} "
          f"episodes x {args.steps} steps, seeds {args.seeds}, {args.workers} workers)")  # fmt: skip

    rng = np.random.default_rng(args.seed)
    rows = []
    total = args.episodes * len(args.learners) * len(args.seeds)
    for i in range(args.kills):
        k = int(rng.integers(-1, total))
        delay = float(rng.uniform(0.0, args.max_delay))
        out = args.out / f"kill{i}"
        r = trial(config, out, k, delay)
        r["identical"] = r["resume_exit_code"] == 0 and same_records(ref, out)
        rows.append(r)
        print(json.dumps(r), flush=True)
        if os.environ.get("SOAK_KEEP") != "1" and r["identical"]:
            shutil.rmtree(out)

    print()
    print("| kill | after episode | + delay [s] | episodes at kill | workers seen | left after wait "
          "| workers gone after [s] | resume exit | identical |")  # fmt: skip
    print("|---|---|---|---|---|---|---|---|---|")
    for i, r in enumerate(rows):
        print(f"| {i} | {r['after_episodes']} | {r['delay_s']} | {r['episodes_at_kill']} | {r['workers_seen']} | "
              f"{r['workers_left_after_wait']} | {r['workers_exit_s']} | "
              f"{r['resume_exit_code']} | {'yes' if r['identical'] else 'NO'} |")  # fmt: skip
    n_ok = sum(r["identical"] for r in rows)
    print(f"\n{n_ok}/{len(rows)} identical to the uninterrupted run; "
          f"{sum(r['workers_left_after_wait'] for r in rows)} workers outlived their study")  # fmt: skip
    (args.out / "soak.json").write_text(
        json.dumps(
            {
                "reference_startup_s": startup,
                "reference_wall_s": wall,
                "args": vars(args) | {"out": str(args.out)},
                "trials": rows,
            },
            indent=2,
        )  # fmt: skip
    )
    if n_ok != len(rows):
        raise SystemExit(1)


if __name__ == "__main__":
    main()
