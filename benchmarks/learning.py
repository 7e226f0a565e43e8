"""Learning benchmark: mpc-rl, bo, mobo (and hybrid) on the CSTR, several seeds, one budget.

Runs the real study runner (``mpcmobo.experiment.run_study``) and prints a markdown table:
episodes until the evaluated incumbent is within 5% and 2% of J*, the final J_eval/J*,
constraint violation during learning, and wall time per episode split into MPC and learner.

    .venv/bin/python benchmarks/learning.py --episodes 50 --seeds 0 1 2 3 4 --out runs/bench-learning
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

from mpcmobo.experiment.settings import load_settings
from mpcmobo.experiment.study import run_study


def table(out: Path) -> str:
    summary = json.loads((out / "summary.json").read_text())
    df = pd.read_parquet(out / "episodes.parquet")
    J_star = summary["J_star"]
    lines = [
        f"J* = {J_star:.1f}, J_eval(theta0) = {summary['J_initial']:.1f} "
        f"(ratio {summary['J_initial'] / J_star:.2f})",
        "",
        "| learner | seeds | episodes to 5% (median, per seed) | episodes to 2% (median, per seed) "
        "| final J_eval/J* (median, per seed) | violation per episode (mean) "
        "| MPC s/episode | learner s/episode |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name, s in summary["learners"].items():
        per = s["per_seed"]
        seeds = sorted(per, key=int)
        to5 = [per[k]["episodes_to_5pct"] for k in seeds]
        to2 = [per[k]["episodes_to_2pct"] for k in seeds]
        ratio = [
            per[k]["J_final"] / J_star if per[k]["J_final"] is not None else np.nan for k in seeds
        ]
        d = df[df["learner"] == name]

        def fmt(v):
            return "-" if v is None else str(v)

        lines.append(
            f"| {name} | {len(seeds)} | {fmt(s['episodes_to_5pct'])} ({', '.join(map(fmt, to5))}) "
            f"| {fmt(s['episodes_to_2pct'])} ({', '.join(map(fmt, to2))}) "
            f"| {np.nanmedian(ratio):.3f} ({', '.join(f'{r:.2f}' for r in ratio)}) "
            f"| {d['violation'].mean():.3g} | {d['mpc_time_s'].mean():.2f} "
            f"| {d['learner_time_s'].mean():.2f} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--learners", nargs="+", default=["mpc-rl", "bo", "mobo", "hybrid"])
    ap.add_argument("--episodes", type=int, default=50)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3, 4])
    ap.add_argument("--eval-every", type=int, default=5)
    ap.add_argument("--start-mode", default="random", choices=["random", "cycle"])
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--out", type=Path, default=Path("runs/bench-learning"))
    ap.add_argument("--table-only", action="store_true", help="only print the table of --out")
    args = ap.parse_args()
    if not args.table_only:
        settings = load_settings(
            None,
            learners=args.learners,
            episodes=args.episodes,
            seeds=args.seeds,
            workers=args.workers,
            start_mode=args.start_mode,
            evaluation={"eval_every": args.eval_every},
        )
        resume = (args.out / "config.toml").exists()
        run_study(None if resume else settings, args.out, resume=resume)
    print(table(args.out))


if __name__ == "__main__":
    main()
