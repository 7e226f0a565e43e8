"""J_eval of every distinct theta a learner ran, to tell search from decision (issue 11).

A learner that is late to reach J* either never ran a good theta (its search) or ran one and did
not deploy it (its decision rule). This script evaluates offline, on the run's own evaluation
starts, every distinct theta one job ran in its first ``--episodes`` episodes, and prints when
each was first run, how many episodes it got, and its J_eval/J*; then, for each threshold, the
first episode that ran a theta within it. With ``--compare A B`` it also lists the episode
costs (f1) of the thetas run at episodes A and B by cycled start (start = episode modulo
``n_cycle_starts``), the learner's own evidence for choosing between them. Nothing
here feeds back into a learner.

    .venv/bin/python benchmarks/candidates.py --out runs/default --learner mobo --episodes 170 --compare 48 56
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

from mpcmobo.experiment.evaluation import make_evaluator
from mpcmobo.experiment.settings import Settings, build_system, load_settings


def _key(theta) -> tuple:
    return tuple(np.round(np.asarray(theta, float), 9))


def _job(out: Path, learner: str, seed: int) -> pd.DataFrame:
    """One job's episode rows, in episode order."""
    df = pd.read_parquet(out / "episodes.parquet")
    job = df[(df.learner == learner) & (df.seed == seed)].sort_values("episode")
    if job.empty:
        raise SystemExit(f"no episodes of learner {learner!r}, seed {seed} in {out}")
    return job


def candidates(out: Path, settings: Settings, job: pd.DataFrame, episodes: int) -> list[dict]:
    """One row per distinct theta of the job's first ``episodes`` episodes."""
    ev = make_evaluator(settings, build_system(settings))
    J_star = json.loads((out / "summary.json").read_text())["J_star"]
    seen: dict[tuple, dict] = {}  # in order of first run
    for e, theta in zip(job.episode, job.theta):
        if e >= episodes:
            break
        row = seen.setdefault(_key(theta), {"first": int(e), "runs": 0, "theta": theta})
        row["runs"] += 1
    return [
        {"first": r["first"], "runs": r["runs"], "J_eval_rel": ev.J_eval(r["theta"]) / J_star}
        for r in seen.values()
    ]


def by_start(job: pd.DataFrame, episode: int, n_starts: int) -> dict[int, list[float]]:
    """The f1 of every episode of the theta run at ``episode``, by cycled start."""
    key = _key(job[job.episode == episode].theta.iloc[0])
    starts: dict[int, list[float]] = {}
    for e, theta, f1 in zip(job.episode, job.theta, job.f1):
        if _key(theta) == key:
            starts.setdefault(int(e) % n_starts, []).append(float(f1))
    return dict(sorted(starts.items()))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True, help="a run directory")
    p.add_argument("--learner", default="mobo")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--episodes", type=int, default=200, help="the first N episodes")
    p.add_argument("--thresholds", type=float, nargs="+", default=[1.02, 1.05, 1.10, 1.5])
    p.add_argument("--compare", type=int, nargs=2, metavar=("A", "B"))
    p.add_argument("--json", type=Path, help="also write the rows here")
    a = p.parse_args()
    settings = load_settings(a.out / "config.toml")
    job = _job(a.out, a.learner, a.seed)
    rows = candidates(a.out, settings, job, a.episodes)
    print(f"{len(rows)} distinct thetas in the first {a.episodes} episodes")
    print("| first episode | episodes | J_eval/J* |\n|---|---|---|")
    for r in rows:
        print(f"| {r['first']} | {r['runs']} | {r['J_eval_rel']:.3f} |")
    for t in a.thresholds:
        hit = [r for r in rows if r["J_eval_rel"] <= t]
        first = f"episode {hit[0]['first']} ({hit[0]['runs']} episodes of it)" if hit else "none"
        print(f"first theta within {t:g} x J*: {first}")
    if a.compare:
        for e in a.compare:
            costs = by_start(job, e, settings.n_cycle_starts)
            cycle = sum(float(np.mean(v)) for v in costs.values())
            shown = ", ".join(f"{s}: {np.mean(v):.0f} ({len(v)})" for s, v in costs.items())
            print(f"theta of episode {e}, mean f1 by start (episodes): {shown}; sum {cycle:.0f}")
    if a.json:
        a.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
