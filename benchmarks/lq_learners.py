"""One learner on one seed of the `lq` system, as a study runs it, with J_eval every 5 episodes.

    PYTHONPATH=src .venv/bin/python benchmarks/lq_learners.py LEARNER SEED EPISODES \
        ['{"option": value}'] [random|cycle]

The harness of docs/benchmarks.md, "GP learners on `lq` (session 6)": the learner is built and
run as `mpcmobo run --system lq` builds and runs it (the default settings, the imperfect model,
the study's exploration), and J_eval of its deployed theta is measured every 5 episodes on the
study's 10 evaluation starts (seed 2025). It prints one JSON line: the final and worst J_eval/J*
of the deployed theta, its curve, the best J_eval/J* of the thetas it ran and how many of them
were better than theta0. Lighter than `benchmarks/learning.py` (no records, no peers).
"""

from __future__ import annotations

import json
import sys
import time

import numpy as np
import torch

from mpcmobo.bo.context import ContextSpec
from mpcmobo.experiment.evaluation import Evaluator
from mpcmobo.experiment.loop import LearningRun
from mpcmobo.experiment.settings import load_settings
from mpcmobo.learners import make_learner
from mpcmobo.mpc import ParametricMPC
from mpcmobo.systems import get_system


def main() -> None:
    """Run LEARNER on SEED for EPISODES episodes and print the JSON line."""
    torch.set_num_threads(1)  # as in a study's worker
    name, seed, episodes = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    options = json.loads(sys.argv[4]) if len(sys.argv) > 4 else {}
    start_mode = sys.argv[5] if len(sys.argv) > 5 else "random"
    settings = load_settings(None, system={"name": "lq"}).resolved()
    system = get_system("lq")
    space, theta0 = system.search_space, system.parameterization.theta0
    evaluator = Evaluator(system, n_starts=10, seed=2025, steps=settings.steps)
    J_star, J0 = evaluator.J_star(), evaluator.J_eval(None)
    if name != "mpc-rl":
        options = {"contexts": ContextSpec.from_system(system), **options}
    learner = make_learner(name, space, theta0, seed=seed, **options)
    mpc = ParametricMPC(system, model="imperfect", **settings.mpc.options())
    run = LearningRun(system, learner, mpc, seed=seed, steps=settings.steps,
                      exploration_std=settings.exploration.std, start_mode=start_mode,
                      n_cycle_starts=settings.n_cycle_starts)  # fmt: skip
    t0, curve, worst, ran = time.time(), [], J0, []
    for k in range(episodes):
        row, _ = run.run_episode()
        ran.append(np.array(row["theta"]))
        if (k + 1) % 5 == 0:
            j = evaluator.J_eval(learner.incumbent())
            curve.append(j / J_star)
            worst = max(worst, j)
    ran_j = [evaluator.J_eval(th) / J_star for th in ran]
    print(json.dumps({
        "learner": name, "seed": seed, "opts": options if name == "mpc-rl" else
        {k: v for k, v in options.items() if k != "contexts"},
        "final": curve[-1] if curve else None, "worst": worst / J_star,
        "curve": [round(c, 3) for c in curve], "best_proposed": round(min(ran_j), 3),
        "n_better": int(sum(j < J0 / J_star for j in ran_j)), "s": round(time.time() - t0, 1),
    }))  # fmt: skip


if __name__ == "__main__":
    main()
