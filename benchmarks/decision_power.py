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

Session 15 (``docs/benchmarks.md``, "Longer runs, and a start model for the hot spots"):
``--covariate`` swaps the test's covariate for ``oracle`` (theta0's noise-free plant cost from
each start, a perfect start model) or ``learned`` (:func:`start_effect`, fitted on the
decision's episodes and ``--extra`` others), and the table adds the power at a false rate of 1%
and 3%; ``--hot-spots`` shows where theta0's plant cost exceeds three times its start cost.

    .venv/bin/python benchmarks/decision_power.py collect --json cstr.json runs/bo-rand-a \
        runs/mobo-rand-a
    .venv/bin/python benchmarks/decision_power.py analyse --json cstr.json --better 0.8
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

from mpcmobo.experiment.evaluation import Evaluator, make_evaluator
from mpcmobo.experiment.settings import Settings, build_system, load_settings
from mpcmobo.learners.deploy import adjusted_confidence
from mpcmobo.mpc import model_plant, model_rollout, rollout
from mpcmobo.rl.exploration import GaussianExploration
from mpcmobo.rl.objectives import f1_closed_loop_cost, mean_stage_cost
from mpcmobo.systems.base import System

FRESH_SEED = 4242  # as benchmarks/recheck.py: apart from the evaluation's starts
COVARIATES = ("start_cost", "oracle", "learned")


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


def fresh_evaluator(config: Path) -> tuple[Settings, System, Evaluator]:
    """A run's settings and system, and an evaluator on 100 fresh starts (``FRESH_SEED``)."""
    settings = load_settings(config)
    system = build_system(settings)
    return settings, system, make_evaluator(settings, system, n_starts=100, seed=FRESH_SEED)


def collect(args: argparse.Namespace) -> None:
    settings, system, ev = fresh_evaluator(args.runs[0] / "config.toml")
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
    out: dict = {
        "start_cost": s,
        "starts": np.asarray(ev.starts).tolist(),
        "state_names": list(system.state_names),
        "thetas": {},
    }
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


def start_effect(x: np.ndarray, y: np.ndarray, group: np.ndarray, n_test: int) -> np.ndarray:
    """A start model learned from episodes: ``y = log(f1 / start cost)`` of episodes from scaled
    starts ``x`` (rows), ``group`` the theta each ran, modelled as a per-theta offset (a random
    effect of variance 100 var(y)) plus a smooth function ``g(x)`` (RBF kernel) plus noise.
    Length scale and noise from a grid, chosen by the closed-form leave-one-out error, ``g = 0``
    among the choices. Returns ``exp(g)`` at the first ``n_test`` episodes, each predicted
    without its own episode: the hot-spot factor by which the episode's start is costlier on
    the plant than the start cost says."""
    v = float(np.var(y)) or 1.0
    G = np.equal.outer(group, group).astype(float)
    D = ((x[:, None, :] - x[None, :, :]) ** 2).sum(-1)
    best = None
    for ls in (0.25, 0.5, 1.0, None):
        Kg = v * np.exp(-0.5 * D / ls**2) if ls else np.zeros_like(D)
        for noise in (0.1, 1.0):
            K = Kg + 100.0 * v * G + noise * v * np.eye(len(y))
            Ki = np.linalg.inv(K)
            err = float(np.mean((Ki @ (y - y.mean()) / np.diag(Ki)) ** 2))
            if best is None or err < best[0]:
                best = (err, Kg, Ki)
    _, Kg, Ki = best
    g = np.empty(n_test)
    for i in range(n_test):
        m = np.arange(len(y)) != i
        # K without episode i, inverted from Ki (the block inverse), not solved again
        Ki_m = Ki[np.ix_(m, m)] - np.outer(Ki[m, i], Ki[i, m]) / Ki[i, i]
        g[i] = Kg[i, m] @ Ki_m @ (y[m] - y[m].mean())
    return np.exp(g)


def decision_confidence(
    covariate: str,
    y_d: np.ndarray,
    y_c: np.ndarray,
    i_d: np.ndarray,
    i_c: np.ndarray,
    ctx: dict,
    rng: np.random.Generator,
) -> float:
    """The default test's confidence that the candidate (episodes ``y_c`` from starts ``i_c``)
    is cheaper than the deployed theta (``y_d`` from ``i_d``) with the named covariate:
    ``start_cost`` (the default, EpisodeResult.start_cost); ``oracle`` (theta0's noise-free
    plant f1 from each start: a perfect start model, unavailable to a learner); ``learned``
    (start cost times the hot-spot factor of :func:`start_effect`, fitted on the decision's
    episodes and ``--extra`` episodes of other thetas from random starts, the rest of a run)."""
    S = ctx["S"]
    if covariate == "start_cost":
        return adjusted_confidence(y_d, y_c, S[i_d], S[i_c])
    if covariate == "oracle":
        O = ctx["oracle"]
        return adjusted_confidence(y_d, y_c, O[i_d], O[i_c])
    others, C, n = ctx["others"], ctx["C"], len(i_d) + len(i_c)
    j = rng.integers(len(others), size=ctx["extra"])
    i = rng.integers(len(S), size=ctx["extra"])
    idx = np.concatenate([i_d, i_c, i])
    y_o = np.array([others[a][b] for a, b in zip(j, i, strict=True)])
    y = np.log(np.concatenate([y_d, y_c, y_o]) / S[idx])
    group = np.concatenate([np.zeros(len(i_d)), np.ones(len(i_c)), 2 + j])
    cov = S[idx[:n]] * start_effect(C[idx], y, group, n)
    return adjusted_confidence(y_d, y_c, cov[: len(i_d)], cov[len(i_d) :])


def hot_spots(X: np.ndarray, ratio: np.ndarray, names: list[str]) -> None:
    """Where theta0's plant cost exceeds three times its start cost: each state's median there
    and elsewhere."""
    hot = ratio > 3
    if not hot.any():
        print(f"\ntheta0's plant cost / start cost: median {np.median(ratio):.2f}, never above 3")
        return
    print(
        f"\ntheta0's plant cost / start cost: median {np.median(ratio):.2f}; above 3 on "
        f"{hot.sum()} of {len(ratio)} starts (median there {np.median(ratio[hot]):.1f})"
    )
    print("| state | median on those starts | median elsewhere | range there | range elsewhere |")
    print("|---|---|---|---|---|")
    for k, name in enumerate(names):
        a, b = X[hot, k], X[~hot, k]
        if b.size:
            print(
                f"| {name} | {np.median(a):.4g} | {np.median(b):.4g} | {a.min():.4g}-{a.max():.4g} "
                f"| {b.min():.4g}-{b.max():.4g} |"
            )


def starts_of(d: dict, config: Path | None) -> tuple[np.ndarray, list[str]]:
    """The fresh starts of a collection and the state names (stored by ``collect``; older
    files: rebuilt from the run's ``config.toml``, the same seed)."""
    if "starts" in d:
        return np.asarray(d["starts"], float), list(d["state_names"])
    if config is None:
        raise SystemExit("this JSON has no starts: give --starts-config (a run's config.toml)")
    _, system, ev = fresh_evaluator(config)
    return np.asarray(ev.starts, float), list(system.state_names)


def analyse(args: argparse.Namespace) -> None:
    d = json.loads(args.json.read_text())
    S = np.array(d["start_cost"])
    T = d["thetas"]
    names = [k for k in T if np.all(np.isfinite(T[k]["free_sc"]))]
    J = {k: float(np.mean(T[k]["free_sc"])) for k in names}
    y0 = np.array(T["theta0"]["noisy_f1"])
    ctx: dict = {"S": S, "oracle": np.array(T["theta0"]["free_f1"]), "extra": args.extra}
    if args.covariate == "learned" or args.hot_spots:
        X, state_names = starts_of(d, args.starts_config)
        ctx["C"] = (X - X.min(0)) / np.where(np.ptp(X, 0) > 0, np.ptp(X, 0), 1.0)
        ctx["others"] = [np.array(T[k]["noisy_f1"]) for k in names]
    if args.hot_spots:
        hot_spots(X, ctx["oracle"] / S, state_names)
    rng = np.random.default_rng(1)
    print(
        f"{args.json}: against theta0, better = J < {args.better} J(theta0), confidence 0.9, "
        f"covariate {args.covariate}; power at a false rate of 1% / 3% (the threshold from "
        "the worse thetas' confidences)"
    )
    print("| episodes a side | power | thetas | false | thetas | power at 1% / 3% false |")
    print("|---|---|---|---|---|---|")
    for n in (6, 12, 24, 48):
        conf: dict[bool, list[float]] = {True: [], False: []}
        for better in (True, False):
            ks = [
                k
                for k in names
                if k != "theta0"
                and (J[k] < args.better * J["theta0"] if better else J[k] > J["theta0"])
            ]
            for k in ks:
                y = np.array(T[k]["noisy_f1"])
                for _ in range(args.draws):
                    i0, i1 = rng.choice(len(S), n), rng.choice(len(S), n)
                    conf[better].append(
                        decision_confidence(args.covariate, y0[i0], y[i1], i0, i1, ctx, rng)
                    )
        t, f = np.array(conf[True]), np.array(conf[False])
        matched = [
            np.mean(t > np.quantile(f, 1 - q)) if f.size and t.size else np.nan
            for q in (0.01, 0.03)
        ]
        print(
            f"| {n} | {np.mean(t >= 0.9) if t.size else np.nan:.2f} | {t.size // args.draws} "
            f"| {np.mean(f >= 0.9) if f.size else np.nan:.3f} | {f.size // args.draws} "
            f"| {matched[0]:.2f} / {matched[1]:.2f} |",
            flush=True,
        )
    if args.covariate != "start_cost":
        return

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
    a.add_argument("--covariate", choices=COVARIATES, default="start_cost")
    a.add_argument("--extra", type=int, default=30, help="learned: other episodes of the run")
    a.add_argument("--draws", type=int, default=200, help="resamples per theta")
    a.add_argument("--hot-spots", action="store_true", help="where theta0's plant cost is high")
    a.add_argument("--starts-config", type=Path, help="a run's config.toml (older JSON files)")
    args = ap.parse_args()
    if args.step == "collect":
        collect(args)
    else:
        analyse(args)


if __name__ == "__main__":
    main()
