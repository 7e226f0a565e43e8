"""How well does the start covariate predict an episode's cost, and what does it buy a test?

Issue 11, session 13 (``docs/benchmarks.md``, "Random starts adjusted for their cost"). For
theta0 and the final thetas of one or more run directories, the plant cost (mean stage cost)
from ``--starts`` fresh initial states (their own seed, never the evaluation starts), and
three covariates computed from the start alone: the MPC's value V_theta0(x0), theta0's closed
loop on the MPC's own model (``EpisodeResult.start_cost``, :func:`mpcmobo.mpc.model_rollout`)
and its square. It prints

* per covariate, the share of each theta's cost variance across the starts that a linear fit
  on it explains (R^2; median and smallest over the thetas);
* for every ordered pair of thetas (deployed, candidate), ``--draws`` resamplings of
  ``--runs`` starts per side: how often each test reaches confidence 0.9 for a worse candidate
  ("false") and for one at least ``--better`` times the deployed theta's J ("power"): Welch
  (:func:`~mpcmobo.learners.deploy.unpaired_confidence`), the ANCOVA on all episodes
  (:func:`~mpcmobo.learners.deploy.ancova_confidence`) and the default with its leverage
  guard (:func:`~mpcmobo.learners.deploy.adjusted_confidence`).

    .venv/bin/python benchmarks/start_covariate.py --out runs/mobo-rand-a runs/mobo-rand-b --better 0.8
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import pandas as pd

from mpcmobo.experiment.evaluation import make_evaluator
from mpcmobo.experiment.settings import build_system, load_settings
from mpcmobo.learners.deploy import adjusted_confidence, ancova_confidence, unpaired_confidence
from mpcmobo.mpc import model_plant, model_rollout
from mpcmobo.rl.objectives import mean_stage_cost

FRESH_SEED = 4242  # as benchmarks/recheck.py: apart from the evaluation's starts


def thetas_of(runs: list[Path], theta0: np.ndarray) -> dict[str, np.ndarray]:
    """theta0 and every job's final deployed theta (distinct from theta0)."""
    out = {"theta0": theta0}
    for run in runs:
        df = pd.read_parquet(run / "episodes.parquet")
        for (learner, seed), job in df.groupby(["learner", "seed"]):
            th = np.asarray(job.sort_values("episode")["incumbent"].iloc[-1], float)
            if not np.allclose(th, theta0):
                out[f"{run.name}/{learner}-s{seed}"] = th
    return out


def r2(y: np.ndarray, F: np.ndarray) -> float:
    """Share of the variance of ``y`` a least-squares fit on the columns of ``F`` explains."""
    X = np.column_stack([np.ones(len(y)), F])
    coef, *_ = np.linalg.lstsq(X, y, rcond=None)
    return float(1 - np.var(y - X @ coef) / np.var(y))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, nargs="+", required=True, help="run directories")
    ap.add_argument("--starts", type=int, default=100)
    ap.add_argument("--runs", type=int, default=6, help="episodes per side of a test")
    ap.add_argument("--draws", type=int, default=100, help="resamplings per pair of thetas")
    ap.add_argument("--better", type=float, default=0.8, help="J ratio that counts as better")
    args = ap.parse_args()

    settings = load_settings(args.out[0] / "config.toml")
    system = build_system(settings)
    ev = make_evaluator(settings, system, n_starts=args.starts, seed=FRESH_SEED)
    mpc = ev.mpc()
    theta0 = mpc.check_theta(None)
    thetas = thetas_of(args.out, theta0)
    C = {k: np.array([mean_stage_cost(r) for r in ev.episodes(th)]) for k, th in thetas.items()}
    C = {k: c for k, c in C.items() if np.all(np.isfinite(c))}
    value = np.array([mpc.solve(x, theta0, sensitivities=False).value for x in ev.starts])
    on_model = model_plant(system, mpc)
    model = np.array(
        [
            mean_stage_cost(model_rollout(system, mpc, theta0, x, ev.steps, plant=on_model))
            for x in ev.starts
        ]
    )
    print(f"{system.name}: {len(C)} thetas, {args.starts} fresh starts\n")
    print("| covariate | R^2 median | R^2 smallest |\n|---|---|---|")
    ok = np.isfinite(value)
    for name, F in [
        ("MPC value V_theta0(x0)", value[:, None]),
        ("theta0's closed loop on the model (start_cost)", model[:, None]),
        ("... and its square", np.column_stack([model, model**2 / model.mean()])),
    ]:
        R = [r2(c[ok], F[ok]) for c in C.values()]
        print(f"| {name} | {np.median(R):.2f} | {np.min(R):.2f} |")

    tests = {
        "Welch": lambda yd, yc, sd, sc: unpaired_confidence(yd, yc),
        "ANCOVA, all episodes": ancova_confidence,
        "ANCOVA with the leverage guard (default)": adjusted_confidence,
    }
    counts = {k: np.zeros((2, 2)) for k in tests}  # [false, power] x [hits, decisions]
    rng = np.random.default_rng(0)
    J = {k: c.mean() for k, c in C.items()}
    for a in C:
        for b in C:
            worse, better = J[b] > J[a], J[b] < args.better * J[a]
            if a == b or not (worse or better):
                continue
            row = 0 if worse else 1
            for _ in range(args.draws):
                ia, ib = rng.choice(args.starts, args.runs), rng.choice(args.starts, args.runs)
                for name, test in tests.items():
                    conf = test(C[a][ia], C[b][ib], model[ia], model[ib])
                    counts[name][row] += [float(conf is not None and conf >= 0.9), 1.0]
    print(f"\n{args.runs} episodes a side, {args.draws} draws per pair, confidence 0.9")
    print("| test | false | power |\n|---|---|---|")
    for name, n in counts.items():
        print(f"| {name} | {n[0, 0] / max(n[0, 1], 1):.3f} | {n[1, 0] / max(n[1, 1], 1):.3f} |")


if __name__ == "__main__":
    main()
