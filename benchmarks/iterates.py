"""J_eval of MPC-RL's iterates, next to the theta it deployed (issue 11, item 3).

MPC-RL runs its iterate and deploys its best verified theta; the study evaluates only the
deployed one. This script evaluates the iterate (the theta of every ``--every``-th episode,
as run) of each seed of a run directory on the run's own evaluation starts, and prints per
seed the best and the last iterate against the final deployed theta:

    .venv/bin/python benchmarks/iterates.py runs/mpcrl-cstr-random --every 5

For a learner other than ``mpc-rl`` (``--learner``) the "iterate" is the proposal of the
episode. Evaluations only: nothing feeds back into the run.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from mpcmobo.experiment import storage
from mpcmobo.experiment.evaluation import make_evaluator
from mpcmobo.experiment.settings import build_system, load_settings


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--learner", default="mpc-rl")
    ap.add_argument("--every", type=int, default=5)
    ap.add_argument("--seeds", type=int, nargs="+", default=None, help="default: all")
    args = ap.parse_args()
    settings = load_settings(args.out / "config.toml").resolved()
    system = build_system(settings)
    evaluator = make_evaluator(settings, system)
    summary = json.loads((args.out / "summary.json").read_text())
    J_star, J0 = summary["J_star"], summary["J_initial"]
    df = storage.read_episodes(args.out)
    df = df[df["learner"] == args.learner]
    print(f"J* = {J_star:.5g}, J_eval(theta0) / J* = {J0 / J_star:.3f}")
    print()
    print(
        "| seed | iterate J_eval/J* at episodes "
        f"{', '.join(str(e) for e in range(args.every, settings.episodes + 1, args.every))} "
        "| best iterate | final deployed | final deployed / best iterate |"
    )
    print("|---|---|---|---|---|")
    ratios = []
    for seed in sorted(df["seed"].unique()) if args.seeds is None else args.seeds:
        d = df[df["seed"] == seed].set_index("episode")
        values = []
        for e in range(args.every, settings.episodes + 1, args.every):
            # the theta run in episode e (the iterate after e steps)
            theta = np.asarray(d.loc[min(e, d.index.max()), "theta"], float)
            values.append(evaluator.J_eval(theta) / J_star)
        final = d["J_eval_incumbent"].dropna().iloc[-1] / J_star
        best = min(values)
        ratios.append(final / best)
        print(
            f"| {seed} | {', '.join(f'{v:.2f}' for v in values)} | {best:.2f} | {final:.2f} "
            f"| {final / best:.2f} |",
            flush=True,
        )
    print()
    print(f"final deployed / best iterate: median {np.median(ratios):.2f}, worst {max(ratios):.2f}")


if __name__ == "__main__":
    main()
