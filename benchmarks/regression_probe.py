"""Where does a regression come from? (issue 11, session 9; CSTR runs).

For the theta a learner had deployed at one episode of a run, runs theta0 and that theta
(the imperfect-model MPC, no exploration) from three sets of initial states: the run's own
cycled starts of that seed, the 10 evaluation starts (J_eval), and ``--fresh`` starts drawn
from the initial-state distribution with their own seed. Prints the mean costs relative to J*
(of the evaluation starts), on how many starts the deployed theta beat theta0, and the median
per-start cost ratio deployed / theta0. docs/benchmarks.md, "Why deployed thetas regress".

    .venv/bin/python benchmarks/regression_probe.py runs/a mobo 9 15
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from mpcmobo.experiment.evaluation import make_evaluator
from mpcmobo.experiment.loop import LearningRun
from mpcmobo.experiment.settings import build_system, load_settings
from mpcmobo.mpc import rollout
from mpcmobo.rl.objectives import mean_stage_cost


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", type=Path)
    ap.add_argument("learner")
    ap.add_argument("seed", type=int)
    ap.add_argument("episode", type=int, help="the deployed theta after this episode")
    ap.add_argument("--fresh", type=int, default=100, help="fresh starts (default 100)")
    ap.add_argument("--fresh-seed", type=int, default=12345)
    args = ap.parse_args()
    settings = load_settings(args.run / "config.toml")
    system = build_system(settings)
    ev = make_evaluator(settings, system)
    mpc = ev.mpc()
    d = pd.read_parquet(args.run / "episodes.parquet")
    row = d[(d.learner == args.learner) & (d.seed == args.seed) & (d.episode == args.episode)]
    if row.empty:
        raise SystemExit(
            f"no episode {args.episode} of {args.learner} seed {args.seed} in {args.run}"
        )
    theta = np.asarray(row.iloc[0].incumbent, float)
    own = LearningRun(
        system,
        None,
        mpc,
        seed=args.seed,
        start_mode="cycle",
        n_cycle_starts=settings.n_cycle_starts,
    ).cycle_starts
    rng = np.random.default_rng(args.fresh_seed)
    fresh = np.array([system.sample_initial_state(rng) for _ in range(args.fresh)])

    def costs(th: np.ndarray | None, starts: np.ndarray) -> np.ndarray:
        return np.array(
            [
                mean_stage_cost(rollout(system, mpc, th, x0, ev.steps, sensitivities=False))
                for x0 in starts
            ]
        )

    J_star = ev.J_star() or 1.0
    for name, starts in (
        ("own cycled", own),
        ("evaluation", ev.starts),
        (f"fresh {args.fresh}", fresh),
    ):
        a, b = costs(None, starts), costs(theta, starts)
        print(
            f"{args.run.name} {args.learner} seed {args.seed} episode {args.episode} | {name}: "
            f"theta0 {a.mean() / J_star:.2f} -> deployed {b.mean() / J_star:.2f}, "
            f"wins {int(np.sum(b < a))}/{len(starts)}, median ratio {np.median(b / a):.2f}"
        )


if __name__ == "__main__":
    main()
