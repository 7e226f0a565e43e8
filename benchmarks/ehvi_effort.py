"""Wall time of one mobo proposal on real CSTR data, for several EHVI search efforts.

Loads the mobo learner of a finished (or interrupted) run from its checkpoint, conditions its
GPs on all recorded episodes, and times ``MOBOLearner._acquire`` (posterior front, box
decomposition, qLogEHVI optimisation) for each effort ``(mc_samples, num_restarts,
raw_samples)``, interleaved over the same acquisition seeds so that every setting sees the same
machine load, with one torch thread as in a study's worker. Also times one conditioning fit and
one full refit (hyperparameters plus the joint start-offset fit) of the same data. Speed-ups
are ratios against the first effort, measured in the same run.

    .venv/bin/python benchmarks/ehvi_effort.py runs/default            # after `mpcmobo run`
    .venv/bin/python benchmarks/ehvi_effort.py runs/default --seeds 5
"""

from __future__ import annotations

import argparse
import os
import pickle
import statistics
import time
from dataclasses import replace
from pathlib import Path

import torch

from mpcmobo.experiment.settings import build_system, load_settings
from mpcmobo.learners import make_learner

EFFORTS = [(64, 4, 256), (32, 2, 128), (32, 4, 256), (64, 2, 128)]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("run", type=Path, help="a run directory with jobs/mobo-s<seed>/")
    p.add_argument("--job", default="mobo-s0")
    p.add_argument("--seeds", type=int, default=5, help="acquisition seeds per effort")
    args = p.parse_args()
    torch.set_num_threads(1)  # as in a study's worker (mpcmobo.experiment.study)

    ckpt = pickle.loads((args.run / "jobs" / args.job / "checkpoint.pkl").read_bytes())
    state = ckpt["state"]["learner"]
    settings = load_settings(args.run / "config.toml")
    system = build_system(settings)
    learner = make_learner(
        "mobo",
        system.search_space,
        system.parameterization.theta0,
        seed=state["seed"],
        **settings.learner_options.get("mobo", {}),
    )
    learner.load_state_dict(state)
    learner.reduce_effort_after = None  # time each effort as given, never its halved form
    sur = learner.surrogate
    n = learner.Z_.shape[0]
    print(f"{args.run}/{args.job}: {n} observations, load avg {os.getloadavg()[0]:.1f}")

    t0 = time.perf_counter()
    sur.fit(learner.Z_, learner.Y_, learner.starts_)  # conditioning only (hyperparameters kept)
    t_cond = time.perf_counter() - t0
    hyper_state = sur.state_dict()
    sur._calls_since_refit = 10**9  # force the next fit to be a full refit
    t0 = time.perf_counter()
    sur.fit(learner.Z_, learner.Y_, learner.starts_)
    t_full = time.perf_counter() - t0
    sur.load_state_dict(hyper_state)  # back to the run's own hyperparameters
    sur.fit(learner.Z_, learner.Y_, learner.starts_)
    learner._acquire(10**6)  # warm-up (posterior caches, lazy imports)

    times: dict[tuple[int, int, int], list[float]] = {e: [] for e in EFFORTS}
    for seed in range(args.seeds):
        for e in EFFORTS:
            learner.ehvi = replace(learner.ehvi, mc_samples=e[0])
            learner.search = replace(learner.search, num_restarts=e[1], raw_samples=e[2])
            t0 = time.perf_counter()
            learner._acquire(seed)
            times[e].append(time.perf_counter() - t0)

    print(f"conditioning fit: {t_cond:.2f} s, full refit (with start offsets): {t_full:.2f} s")
    print()
    print(
        "| mc_samples | num_restarts | raw_samples | proposal median [s] | min-max [s] | speed-up |"
    )
    print("|---|---|---|---|---|---|")
    base = statistics.median(times[EFFORTS[0]])
    for e in EFFORTS:
        med = statistics.median(times[e])
        print(
            f"| {e[0]} | {e[1]} | {e[2]} | {med:.2f} | {min(times[e]):.2f}-{max(times[e]):.2f} "
            f"| {base / med:.1f}x |"
        )


if __name__ == "__main__":
    main()
