"""How many episodes does a deployment decision need under random starts?

Issue 11, session 14 (``docs/benchmarks.md``, "Screening candidates relative to their
starts"). Two steps:

``collect``: for theta0 and thetas of one or more run directories (each job's final deployed
theta and every theta it ran at least twice, i.e. the candidates it verified; at most
``--max-thetas``), the episode from each of 100 fresh starts (seed 4242, never the evaluation
starts) twice: noise-free, and with the run's exploration noise as a learner's episodes have it
(:class:`~mpcmobo.rl.exploration.GaussianExploration`, its own seed per theta and start); f1 and
the mean stage cost of each, and the start cost of every start (theta0's closed loop on the
MPC's own model, the covariate of :func:`~mpcmobo.learners.deploy.adjusted_confidence`). Written
to ``--json`` after every theta.

``analyse``: resampling episodes from those starts (200 draws per theta),

* against theta0, per number of episodes a side (6, 12, 24, 48): how often the default test
  (:func:`~mpcmobo.learners.deploy.adjusted_confidence`, confidence 0.9, on f1 of exploring
  episodes) deploys a theta with J (mean stage cost without noise, as J_eval) below ``--better``
  times theta0's ("power") and one above theta0's ("false");
* over all ordered pairs, 6 episodes a side (100 draws): the same rates for exploring and for
  noise-free episodes (does measuring a theta without exploration noise help the test?).

    .venv/bin/python benchmarks/decision_power.py collect --json cstr.json runs/bo-rand-a runs/mobo-rand-a
    .venv/bin/python benchmarks/decision_power.py analyse --json cstr.json --better 0.8
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

from mpcmobo.experiment.evaluation import make_evaluator
from mpcmobo.experiment.settings import build_system, load_settings
from mpcmobo.learners.deploy import adjusted_confidence
from mpcmobo.mpc import model_plant, model_rollout, rollout
from mpcmobo.rl.exploration import GaussianExploration
from mpcmobo.rl.objectives import f1_closed_loop_cost, mean_stage_cost

FRESH_SEED = 4242  # as benchmarks/recheck.py: apart from the evaluation's starts


def thetas_of(runs: list[Path], theta0: np.ndarray) -> dict[str, np.ndarray]:
    """theta0, then per job its final deployed theta and the thetas it ran at least twice."""
    thetas = {"theta0": theta0}
    for run in runs:
        df = pd.read_parquet(run / "episodes.parquet")
        for (learner, seed), job in df.groupby(["learner", "seed"]):
            counts: dict[bytes, list] = {}
            for t in job.theta:
                t = np.asarray(t, float)
                counts.setdefault(t.tobytes(), [t, 0])[1] += 1
            final = np.asarray(job.sort_values("episode")["incumbent"].iloc[-1], float)
            picks = [final] + [t for t, n in counts.values() if n >= 2]
            for i, t in enumerate(picks):
                if not any(np.allclose(t, u) for u in thetas.values()):
                    thetas[f"{run.name}/{learner}-s{seed}-{i}"] = t
    return thetas


def collect(args: argparse.Namespace) -> None:
    settings = load_settings(args.runs[0] / "config.toml")
    system = build_system(settings)
    ev = make_evaluator(settings, system, n_starts=100, seed=FRESH_SEED)
    mpc = ev.mpc()
    theta0 = mpc.check_theta(None)
    thetas = thetas_of(args.runs, theta0)
    names = list(thetas)[: args.max_thetas]
    std = np.asarray(settings.exploration.std, float)
    std = np.broadcast_to(std, (system.nu,)) if std.size == 1 else std
    on_model = model_plant(system, mpc)
    s = [
        mean_stage_cost(model_rollout(system, mpc, theta0, x, ev.steps, plant=on_model))
        for x in ev.starts
    ]
    out: dict = {"start_cost": s, "thetas": {}}
    for ti, name in enumerate(names):
        th = thetas[name]
        rec: dict = {"theta": th.tolist()}
        rec.update({k: [] for k in ("free_f1", "free_sc", "noisy_f1", "noisy_sc")})
        for i, x0 in enumerate(ev.starts):
            r = rollout(
                system, mpc, th, x0, ev.steps, sensitivities=False, plant_seed=ev.plant_seed(i)
            )
            rec["free_f1"].append(f1_closed_loop_cost(r))
            rec["free_sc"].append(mean_stage_cost(r))
            r = rollout(
                system,
                mpc,
                th,
                x0,
                ev.steps,
                sensitivities=False,
                rng=np.random.default_rng([ti, i, 7]),
                exploration=GaussianExploration(std=std),
                plant_seed=ev.plant_seed(i) + 1,
            )
            rec["noisy_f1"].append(f1_closed_loop_cost(r))
            rec["noisy_sc"].append(mean_stage_cost(r))
        out["thetas"][name] = rec
        print(name, np.mean(rec["free_sc"]), np.mean(rec["noisy_sc"]), flush=True)
        args.json.write_text(json.dumps(out))


def analyse(args: argparse.Namespace) -> None:
    d = json.loads(args.json.read_text())
    S = np.array(d["start_cost"])
    T = d["thetas"]
    names = [k for k in T if np.all(np.isfinite(T[k]["free_sc"]))]
    J = {k: float(np.mean(T[k]["free_sc"])) for k in names}
    y0 = np.array(T["theta0"]["noisy_f1"])
    rng = np.random.default_rng(1)
    print(f"{args.json}: against theta0, better = J < {args.better} J(theta0), confidence 0.9")
    print("| episodes a side | power | thetas | false | thetas |\n|---|---|---|---|---|")
    for n in (6, 12, 24, 48):
        rates = []
        for better in (True, False):
            ks = [
                k
                for k in names
                if k != "theta0"
                and (J[k] < args.better * J["theta0"] if better else J[k] > J["theta0"])
            ]
            hits = total = 0
            for k in ks:
                y = np.array(T[k]["noisy_f1"])
                for _ in range(200):
                    i0, i1 = rng.choice(len(S), n), rng.choice(len(S), n)
                    hits += adjusted_confidence(y0[i0], y[i1], S[i0], S[i1]) >= 0.9
                    total += 1
            rates += [hits / max(total, 1), len(ks)]
        print(f"| {n} | {rates[0]:.2f} | {rates[1]} | {rates[2]:.3f} | {rates[3]} |")

    rng = np.random.default_rng(0)
    print("\nall ordered pairs, 6 episodes a side, confidence 0.9 (false / power)")
    for mode, label in (("noisy_f1", "exploring episodes"), ("free_f1", "noise-free episodes")):
        counts = np.zeros((2, 2))
        for a in names:
            for b in names:
                worse, better = J[b] > J[a], J[b] < args.better * J[a]
                if a == b or not (worse or better):
                    continue
                ya, yb = np.array(T[a][mode]), np.array(T[b][mode])
                for _ in range(100):
                    ia, ib = rng.choice(len(S), 6), rng.choice(len(S), 6)
                    conf = adjusted_confidence(ya[ia], yb[ib], S[ia], S[ib])
                    counts[0 if worse else 1] += [float(conf >= 0.9), 1.0]
        f, p = counts[0, 0] / max(counts[0, 1], 1), counts[1, 0] / max(counts[1, 1], 1)
        print(f"{label}: {f:.3f} / {p:.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="step", required=True)
    c = sub.add_parser("collect")
    c.add_argument("--json", type=Path, required=True)
    c.add_argument("--max-thetas", type=int, default=16)
    c.add_argument("runs", type=Path, nargs="+", help="run directories")
    a = sub.add_parser("analyse")
    a.add_argument("--json", type=Path, required=True)
    a.add_argument("--better", type=float, default=0.8, help="J ratio that counts as better")
    args = ap.parse_args()
    if args.step == "collect":
        collect(args)
    else:
        analyse(args)


if __name__ == "__main__":
    main()
