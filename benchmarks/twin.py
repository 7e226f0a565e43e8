"""How far the twin's theta carries beyond the starts it was tuned on, and what tuning on the
plant itself reaches beyond `identify`.

Identify-first tunes theta on the twin (``mpcmobo.learners.twin.tune_on_twin``): the ``bo``
learner's evaluations are mean costs of noise-free closed loops on the identified model from
``TWIN_STARTS`` starts. This benchmark runs that tuning on a system whose identified model is
the true one (the reference model, ``true_params``: what the identification reaches on the
noise-free CSTR, within 2e-7) from theta0, for each ``--starts`` count and seed, with the same
starts the learner draws (seed sequence ``[seed, 11]``), and scores the twin's theta against
theta0 on the same model, which is J*'s controller, on three sets of starts: the ones it was
tuned on, ``--fresh`` fresh starts (the seed of ``benchmarks/recheck.py``), the study's 10
evaluation starts and the seed's cycle of starts (the six a cycled study's plant episodes start
from, on which a paired test on the plant judges the twin's theta). So the ratios are J/J* on
each set; below 1 is what a better cost buys beyond the right model (the paper's Theorem 1).
It also gives the tuning's time (one thread).

With ``--from-run DIR`` the same tuning starts instead from each seed's final theta of the
``identify`` learner in the run ``DIR`` (its config, its identified model) and runs on the
plant itself, noise-free (the system's equations with ``true_params``, which on
``cstr-structural`` hold the structure the model lacks): free noise-free plant episodes, many
more than a study has (``--starts 32 --episodes 60``: 1920 per seed). The ratios are then
against `identify`'s theta on the same starts: a reference for what tuning theta can buy
beyond identification alone on each set of starts.

    .venv/bin/python benchmarks/twin.py --config benchmarks/configs/ident.toml \\
        --starts 8 32 --seeds 10 --workers 2 --json runs/twin/twin.json
    .venv/bin/python benchmarks/twin.py --from-run runs/struct --starts 32 --episodes 60 \\
        --seeds 10 --workers 2
"""

from __future__ import annotations

import argparse
import json
import os
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pandas as pd
from recheck import RECHECK_SEED, _thetas  # benchmarks/ is on sys.path when run as a script

from mpcmobo.experiment.build import build_system, identified_parameters
from mpcmobo.experiment.evaluation import make_evaluator
from mpcmobo.experiment.job import single_threaded
from mpcmobo.experiment.loop import model_costs, starts_of_cycle
from mpcmobo.experiment.settings import load_settings
from mpcmobo.identify import ModelFit
from mpcmobo.learners.twin import TWIN_EPISODES, tune_on_twin
from mpcmobo.mpc import ParametricMPC, model_plant


def _job(
    config: str, n_starts: int, seed: int, fresh: int, episodes: int, run: str | None = None
) -> dict:
    """One tuning from theta0 on the true model (or, with ``run``, from that run's `identify`
    theta of ``seed`` on the plant itself), scored on the three sets of starts against the
    theta it starts from."""
    with single_threaded():
        learner = "bo" if run is None else "identify"  # theta with the identified parameters
        settings = load_settings(config if run is None else Path(run) / "config.toml")
        if run is not None and settings.system.plant is not None:
            raise SystemExit(
                f"{run}: the plant is not the system's equations; it has no "
                "noise-free copy to tune on"
            )
        system = build_system(settings, learner)
        if system.true_params is None:
            raise SystemExit(f"the system '{system.name}' has no true model to tune the twin on")
        fit = ModelFit(system, identified_parameters(settings, system, learner))
        mpc = ParametricMPC(system, model="imperfect", **settings.mpc.options())
        true = np.asarray(system.true_params, float)
        start = (
            fit.theta_with(mpc.theta0, true[fit.index])
            if run is None
            else _identify_theta(Path(run), seed)
        )
        plant = model_plant(system, mpc, true)
        steps = system.episode_steps if settings.steps is None else settings.steps

        def costs(starts: np.ndarray, theta: np.ndarray, params: np.ndarray) -> np.ndarray:
            return model_costs(system, mpc, theta, starts, steps, plant)  # params: the plant's

        rng = np.random.default_rng(np.random.SeedSequence([seed, 11]))  # the learner's starts
        tuned_on = np.array([system.sample_initial_state(rng) for _ in range(n_starts)])
        t = time.process_time()
        res = tune_on_twin(system.search_space, start, true, costs, tuned_on, seed, episodes)
        seconds = time.process_time() - t
        sets = {  # on its own starts the tuning has the costs already (res.cost, res.base_cost)
            "fresh": np.asarray(
                make_evaluator(settings, system, n_starts=fresh, seed=RECHECK_SEED).starts
            ),
            "eval": np.asarray(make_evaluator(settings, system).starts),
            "cycle": starts_of_cycle(system, seed, settings.n_cycle_starts, settings.cycle_starts),
        }
        row: dict = {"starts": n_starts, "seed": seed, "seconds": seconds, "better": res.better}
        row["tuned_on"] = res.cost / res.base_cost
        for name, S in sets.items():
            base = costs(S, start, true)
            row[name] = float(np.mean(costs(S, res.theta, true)) / np.mean(base))
        return row


def _identify_theta(run: Path, seed: int) -> np.ndarray:
    """The final deployed theta of the ``identify`` learner's job ``seed`` in ``run`` (as
    ``recheck.py`` picks it)."""
    df = pd.read_parquet(run / "episodes.parquet")
    job = df[(df.learner == "identify") & (df.seed == seed)]
    if job.empty:
        raise SystemExit(f"{run}: no episode of the learner 'identify' with seed {seed}")
    return _thetas(job, ("final",))["final"][0]


def _table(rows: list[dict], start: str = "J*") -> str:
    """Per starts count: median and worst seed on each set (ratios to ``start``, the theta
    the tuning starts from), seeds above it on fresh starts. On its own starts a seed whose
    starting theta fails a closed loop has no ratio and is left out of the median."""
    lines = [
        "| tuned on (starts) | seeds | on its starts (median) | on fresh starts (median, worst) "
        f"| seeds above {start} on fresh starts | on the evaluation starts (median) "
        f"| seeds above {start} on the cycle's starts | time per tuning [s] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for n in sorted({r["starts"] for r in rows}):
        rs = [r for r in rows if r["starts"] == n]
        f = np.array([r["fresh"] for r in rs])
        lines.append(
            f"| {n} | {len(rs)} | {np.nanmedian([r['tuned_on'] for r in rs]):.3f} "
            f"| {np.median(f):.3f}, {f.max():.3f} | {int(np.sum(f > 1.0 + 1e-9))} "
            f"| {np.median([r['eval'] for r in rs]):.3f} "
            f"| {sum(r['cycle'] > 1.0 + 1e-9 for r in rs)} "
            f"| {np.median([r['seconds'] for r in rs]):.0f} |"
        )
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--config", default="benchmarks/configs/ident.toml")
    ap.add_argument("--starts", type=int, nargs="+", default=[8, 32])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--fresh", type=int, default=100)
    ap.add_argument("--episodes", type=int, default=TWIN_EPISODES)
    ap.add_argument("--workers", type=int, default=max(1, (os.cpu_count() or 1)))
    ap.add_argument("--json", type=Path)
    ap.add_argument(
        "--from-run",
        default=None,
        help="tune each seed's `identify` theta of this run on the plant",
    )
    a = ap.parse_args()
    tasks = [
        (a.config, n, s, a.fresh, a.episodes, a.from_run) for n in a.starts for s in range(a.seeds)
    ]
    tasks.sort(key=lambda t: -t[1])  # the long ones first
    with ProcessPoolExecutor(a.workers) as pool:
        rows = list(pool.map(_job, *zip(*tasks)))
    for r in sorted(rows, key=lambda r: (r["starts"], r["seed"])):
        print(json.dumps(r))
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(rows, indent=1))
    print(_table(rows, "J*" if a.from_run is None else "`identify`"))


if __name__ == "__main__":
    main()
