"""Identification alone: how good the identified model is after k episodes, and what a fit costs.

``--out DIR``: for every seed of the run's ``identify`` learner (or ``--learner``), the MPC with
theta0's cost and the model identified after each of its first ``--episodes`` episodes (the
``identified`` column of ``episodes.parquet``), evaluated on the run's evaluation starts
(J_eval/J*, optionally also on ``--fresh`` fresh starts): the table gives per episode the median
and the worst seed, and on how many seeds it is within 1% of J*.

``--fit-time``: the wall time of one fit (``ModelFit.fit``, warm-started as the learners fit)
on the transitions of 1, 10 and 50 exploring episodes of theta0 on the plant, next to the
learners' time per episode read from ``--out``'s records.

    .venv/bin/python benchmarks/identification.py --out runs/ident-cstr --episodes 5
    .venv/bin/python benchmarks/identification.py --out runs/ident-cstr --fit-time
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np
import pandas as pd

from mpcmobo.experiment.build import build_system, identified_parameters
from mpcmobo.experiment.evaluation import make_evaluator
from mpcmobo.experiment.settings import load_settings
from mpcmobo.identify import ModelFit, Transitions
from mpcmobo.mpc import ParametricMPC, rollout
from mpcmobo.rl import GaussianExploration


def quality(out: Path, learner: str, episodes: int, fresh: int) -> str:
    settings = load_settings(out / "config.toml")
    system = build_system(settings, learner)
    fit = ModelFit(system, identified_parameters(settings, system, learner))
    ev = make_evaluator(settings, system)
    J_star = ev.J_star()
    evf = make_evaluator(settings, system, n_starts=fresh, seed=4242) if fresh else None
    Jf_star = evf.J_star() if evf is not None else None
    theta0 = ParametricMPC(system, "imperfect", **settings.mpc.options()).theta0
    df = pd.read_parquet(out / "episodes.parquet")
    df = df[df["learner"] == learner].sort_values(["seed", "episode"])
    rows = []
    for k in range(episodes):
        r, rf = [], []
        for _, job in df.groupby("seed"):
            est = job["identified"].iloc[k]
            theta = fit.theta_with(theta0, np.asarray(est, float))
            r.append(ev.J_eval(theta) / J_star)
            if evf is not None:
                rf.append(evf.J_eval(theta) / Jf_star)
        r = np.array(r)
        line = (
            f"| {k + 1} | {np.median(r):.3f} | {r.max():.3f} | {int(np.sum(r <= 1.01))}/{len(r)} |"
        )
        if rf:
            line += f" {np.median(rf):.3f}, {max(rf):.3f} |"
        rows.append(line)
    head = "| episodes identified from | J_eval/J* (median) | worst seed | within 1% of J* |"
    sep = "|---|---|---|---|"
    if fresh:
        head += f" on {fresh} fresh starts (median, worst) |"
        sep += "---|"
    return "\n".join([head, sep, *rows])


def fit_time(out: Path, learner: str) -> str:
    settings = load_settings(out / "config.toml")
    system = build_system(settings, learner)
    fit = ModelFit(system, identified_parameters(settings, system, learner))
    mpc = ParametricMPC(system, "imperfect", **settings.mpc.options())
    rng = np.random.default_rng(0)
    expl = GaussianExploration(std=np.asarray(settings.resolved().exploration.std))
    data = Transitions.empty(system.nx, system.nu)
    lines = ["| transitions | fit [s] (warm-started) |", "|---|---|"]
    est = None
    for e in range(50):
        x0 = system.sample_initial_state(rng)
        rec = rollout(system, mpc, None, x0, settings.resolved().steps, rng=rng, exploration=expl,
                      sensitivities=False)  # fmt: skip
        data.add_episode(rec.x, rec.u)
        if e in (0, 9, 49):
            if est is None:
                est = fit.fit(data).estimate
            t0 = time.perf_counter()
            est = fit.fit(data, start=est).estimate
            lines.append(f"| {len(data)} | {time.perf_counter() - t0:.3f} |")
    df = pd.read_parquet(out / "episodes.parquet")
    per = df.groupby("learner")["learner_time_s"].mean()
    lines += ["", "| learner | learner s/episode (the run's) |", "|---|---|"]
    lines += [f"| {n} | {v:.3f} |" for n, v in per.items()]
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--learner", default="identify")
    ap.add_argument("--episodes", type=int, default=5)
    ap.add_argument("--fresh", type=int, default=0, help="also on this many fresh starts")
    ap.add_argument("--fit-time", action="store_true")
    args = ap.parse_args()
    if args.fit_time:
        print(fit_time(args.out, args.learner))
    else:
        print(quality(args.out, args.learner, args.episodes, args.fresh))


if __name__ == "__main__":
    main()
