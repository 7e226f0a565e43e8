"""The mobo learner's time per episode, replayed from a finished study, one code against another.

Replays the recorded episodes of one job of a run (``episodes.parquet``: theta, f1..f4, start)
into a fresh learner built with the run's settings, so that the learner is timed alone, without
MPC episodes. One episode of a study's learner is ``propose()``, then ``observe()`` of the
episode's outcome and ``incumbent()`` (``mpcmobo.experiment.loop``); this is what is timed.
The job must learn from its plant episodes alone: a run without identification and without an
exploration budget, as the paper's protocol (``benchmarks/configs/paper.toml``); another job
is refused with the reason.

1. States: the learner's state before each sampled episode ``i`` (every ``--stride``-th from
   ``--offset``, from ``--first`` on) is the job's final checkpoint with its data cut to the
   first ``i`` episodes. The GPs keep the run's final hyperparameters and start offsets (those
   it had at ``i`` would take a replay of all full refits), and the state is set so that the
   timed episode conditions the GPs (no full refit: refits are a separate, unchanged cost; the
   study's records list them). Cached in ``--states``.
2. Time: one worker process per ``--src`` tree (each with ``PYTHONPATH=<src>``), fed the same
   sampled episodes in alternation (A, B, A, B, ...), so that both see the same machine load.
   Each loads the state, then times propose + observe + incumbent in CPU time (one thread, as
   in a study's worker: ``mpcmobo.experiment.job.single_threaded``) and in wall time, and
   returns its proposal, so the proposals of the trees are compared bit for bit.

    PYTHONPATH=src .venv/bin/python benchmarks/learner_time.py runs/paper \\
        --src /path/to/old/src --src src --stride 10

Ratios are of the sums over the sampled episodes (the first tree against each other one).
"""

from __future__ import annotations

import argparse
import json
import os
import pickle
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def _learner(run: Path, name: str, seed: int, options: str = ""):  # noqa: ANN202 - a Learner
    """The learner of the run's settings, with ``options`` ("key=value,...", TOML values)
    added to its learner options."""
    import tomllib

    from mpcmobo.experiment.build import build_system
    from mpcmobo.experiment.job import make_study_learner
    from mpcmobo.experiment.settings import load_settings

    settings = load_settings(run / "config.toml")
    extra = tomllib.loads("\n".join(options.split(","))) if options else {}
    if extra:
        opts = {
            **settings.learner_options,
            name: {**settings.learner_options.get(name, {}), **extra},
        }
        settings = settings.model_copy(update={"learner_options": opts})
    system = build_system(settings)
    learner = make_study_learner(settings, system, name, system.parameterization.theta0, seed)
    return learner, settings


def _rows(run: Path, name: str, seed: int) -> list[dict]:
    import pandas as pd

    df = pd.read_parquet(run / "episodes.parquet")
    df = df[(df.learner == name) & (df.seed == seed)].sort_values("episode")
    return df.to_dict("records")


def _result(row: dict, n_cycle: int, start_mode: str, n_theta: int):  # noqa: ANN202
    from mpcmobo.learners.base import EpisodeResult

    return EpisodeResult(
        objectives=np.array([row["f1"], row["f2"], row["f3"], row["f4"]], float),
        grad=np.zeros(n_theta),
        critic_ok=bool(row["critic_ok"]),
        start_id=int(row["episode"]) % n_cycle if start_mode == "cycle" else -1,
        x0=np.asarray(row["x0"], float),
        violation=float(row["violation"]),
        start_cost=float(row.get("start_cost", np.nan)),
    )


def record(args: argparse.Namespace) -> dict:
    """The learner's state before each sampled episode ``i``: the job's final checkpoint with
    its evidence cut to the first ``i`` episodes; the GPs' hyperparameters and start offsets
    are the final ones (a conditioning fit is due, not a full refit)."""
    from mpcmobo.experiment.storage import read_pickle

    ckpt = read_pickle(args.run / "jobs" / f"{args.learner}-s{args.seed}" / "checkpoint.pkl")
    final = ckpt["state"]["learner"]
    if "evidence" not in final:
        raise SystemExit(
            f"{args.run}: the job {args.learner}-s{args.seed} identifies its model first; "
            f"replay a run without identification ([system] identify = false)"
        )
    n = len(final["evidence"]["Z"])
    episodes = len(_rows(args.run, args.learner, args.seed))
    if n != episodes:
        raise SystemExit(
            f"{args.run}: the job {args.learner}-s{args.seed} learned from {n} episodes, "
            f"{episodes} ran on the plant (the exploration budget's simulated candidates); "
            f"replay a run without the budget ([exploration] budget = inf)"
        )
    states = {}
    for i in range(args.offset, n, args.stride):
        if i < args.first:
            continue
        st = dict(final)
        st["evidence"] = {
            key: (v[:i] if len(v) == n else v) if isinstance(v, list | np.ndarray) else v
            for key, v in final["evidence"].items()
        }
        sur = dict(final["surrogate"])
        sur["calls_since_refit"] = 0  # the replayed fit and the timed one only condition
        st["surrogate"] = sur
        st["pending"] = None
        st["n_observed"] = i
        states[i] = pickle.dumps(st)
    return {"states": states, "n": n}


def serve(args: argparse.Namespace) -> None:
    """Worker: read episode indices on stdin, answer one JSON line each."""
    from mpcmobo.experiment.job import single_threaded

    data = pickle.loads(Path(args.states).read_bytes())
    rows = _rows(args.run, args.learner, args.seed)
    _, settings = _learner(args.run, args.learner, args.seed, args.options)
    with single_threaded():
        for line in sys.stdin:
            i = int(line)  # negative: a warm-up of episode -i (lazy imports, kernels)
            learner, _ = _learner(args.run, args.learner, args.seed, args.options)
            learner.load_state_dict(pickle.loads(data["states"][abs(i)]))
            row = rows[abs(i)]
            theta = np.asarray(row["theta"], float)
            res = _result(row, settings.n_cycle_starts, settings.start_mode, len(theta))
            c0, w0 = time.process_time(), time.perf_counter()
            prop = learner.propose()
            c1 = time.process_time()
            learner.observe(theta, res)
            learner.incumbent()
            c2, w2 = time.process_time(), time.perf_counter()
            out = {
                "i": i,
                "propose_cpu": c1 - c0,
                "observe_cpu": c2 - c1,
                "cpu": c2 - c0,
                "wall": w2 - w0,
                "proposal": [float(v).hex() for v in prop],
            }
            print(json.dumps(out), flush=True)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run", type=Path, help="a finished run directory (episodes.parquet)")
    p.add_argument("--learner", default="mobo")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--src",
        action="append",
        default=[],
        help="a src tree to time (repeat); SRC::key=value,... adds learner options",
    )
    p.add_argument("--options", default="", help=argparse.SUPPRESS)
    p.add_argument("--stride", type=int, default=10, help="time every stride-th episode")
    p.add_argument("--offset", type=int, default=5, help="sample episodes offset + k stride")
    p.add_argument("--first", type=int, default=20, help="first sampled episode (GPs refit below)")
    p.add_argument("--states", default=None, help="cache of the recorded states")
    p.add_argument("--serve", action="store_true", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.states is None:
        key = f"{args.run.name}_{args.learner}{args.seed}_{args.stride}_{args.offset}_{args.first}"
        args.states = f"/tmp/learner_time_{key}.pkl"
    if args.serve:
        serve(args)
        return
    if not Path(args.states).exists():
        Path(args.states).write_bytes(pickle.dumps(record(args)))
    data = pickle.loads(Path(args.states).read_bytes())
    episodes = sorted(data["states"])
    srcs = args.src or [str(Path(__file__).resolve().parents[1] / "src")]
    print(
        f"{args.run}: {args.learner} seed {args.seed}, {data['n']} episodes, {len(episodes)} "
        f"sampled (every {args.stride}th from {episodes[0]}), "
        f"load avg {os.getloadavg()[0]:.1f}"
    )
    workers = []
    for spec in srcs:
        src, _, options = spec.partition("::")
        env = {**os.environ, "PYTHONPATH": src}
        cmd = [sys.executable, __file__, str(args.run), "--serve", "--states", args.states,
               "--learner", args.learner, "--seed", str(args.seed), "--options", options]  # fmt: skip
        workers.append(
            subprocess.Popen(cmd, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
        )
    for w in workers:  # warm-up, not timed
        w.stdin.write(f"{-episodes[0]}\n")  # type: ignore[union-attr]
        w.stdin.flush()  # type: ignore[union-attr]
    for w in workers:
        w.stdout.readline()  # type: ignore[union-attr]
    res: list[list[dict]] = [[] for _ in srcs]
    for k, i in enumerate(episodes):
        order = range(len(srcs)) if k % 2 == 0 else reversed(range(len(srcs)))
        for w in order:
            workers[w].stdin.write(f"{i}\n")  # type: ignore[union-attr]
            workers[w].stdin.flush()  # type: ignore[union-attr]
            res[w].append(json.loads(workers[w].stdout.readline()))  # type: ignore[union-attr]
        line = "  ".join(f"{r[-1]['cpu']:.2f}" for r in res)
        print(f"  episode {i}: cpu [s] {line}", flush=True)
    for w in workers:
        w.stdin.close()  # type: ignore[union-attr]
        w.wait()
    print()
    print(
        "| tree | sampled | CPU sum [s] | CPU mean [s] | propose mean [s] | observe mean [s] | wall sum [s] | CPU ratio | same proposals |"
    )
    print("|---|---|---|---|---|---|---|---|---|")
    base = sum(r["cpu"] for r in res[0])
    for src, r in zip(srcs, res, strict=True):
        cpu = sum(x["cpu"] for x in r)
        same = sum(a["proposal"] == b["proposal"] for a, b in zip(res[0], r, strict=True))
        print(
            f"| {src} | {len(r)} | {cpu:.1f} | {cpu / len(r):.3f} | "
            f"{np.mean([x['propose_cpu'] for x in r]):.3f} | "
            f"{np.mean([x['observe_cpu'] for x in r]):.3f} | {sum(x['wall'] for x in r):.1f} | "
            f"{base / cpu:.2f}x | {same}/{len(r)} |"
        )
    by_stage = {}
    for k, i in enumerate(episodes):
        by_stage.setdefault(i // 100, []).append(k)
    print()
    print(
        "| episodes | "
        + " | ".join(f"CPU mean {Path(s).parent.name or s} [s]" for s in srcs)
        + " |"
    )
    print("|---|" + "---|" * len(srcs))
    for st, ks in sorted(by_stage.items()):
        means = [np.mean([res[w][k]["cpu"] for k in ks]) for w in range(len(srcs))]
        print(f"| {100 * st}-{100 * st + 99} | " + " | ".join(f"{m:.3f}" for m in means) + " |")


if __name__ == "__main__":
    main()
