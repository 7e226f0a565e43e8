"""The numbers of docs/reproduction.md, claim by claim, from run directories.

    PYTHONPATH=src .venv/bin/python benchmarks/reproduction.py runs/paper runs/default \
        --labels paper default

Reads each run's ``episodes.parquet``, ``trajectories.parquet`` and ``summary.json`` (as written
by ``mpcmobo run``) and prints Markdown tables, one per claim of the paper's section 5:

1. Fig. 1, ranking and speed: per learner, the final and the best J_eval/J* of the deployed theta,
   the episodes until it was first within 10%, 5% and 2% of J*, and the mean J~ of the last 100
   episodes against J~* (the like-for-like reference of the training curve).
2. Fig. 2, |A^w| going to zero: the mean |A^w| per episode of MPC-RL and MOBO over windows of
   episodes (median over seeds; episodes without a critic left out), and MOBO's over MPC-RL's.
3. Figs. 3-4, trajectories within the limits: how far the states and inputs of the stored
   episodes went outside their limits, for theta0, the learned theta and the perfect model.
4. Safety during learning: the plant's constraint violation per learning episode, the episodes
   with a violation, solver failures, and the deployed theta against theta0 (regressions).

Medians over seeds, with the worst seed; every figure is per seed where it says so.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

from mpcmobo.plots import deployed_J_eval

WINDOWS = [(0, 50), (50, 200), (200, 400), (400, 600)]


def load(run: Path) -> tuple[pd.DataFrame, pd.DataFrame, dict]:
    """Episodes, trajectories and summary of one run directory (of a stopped run: the
    learners that have episodes)."""
    ep = pd.read_parquet(run / "episodes.parquet")
    tr = pd.read_parquet(run / "trajectories.parquet")
    s = json.loads((run / "summary.json").read_text())
    s["learners"] = {k: v for k, v in s["learners"].items() if (ep.learner == k).any()}
    return ep, tr, s


def first_within(d: pd.DataFrame, target: float) -> int | None:
    """The first episode whose deployed J_eval <= target: its index, counted from 0 as
    ``summary.json``'s ``episodes_to_2pct`` counts it."""
    hit = d[d["J_eval_incumbent"] <= target]
    return None if hit.empty else int(hit["episode"].iloc[0])


def fmt(v: float | None, nd: int = 2) -> str:
    """A number for a table ('-' for missing)."""
    if v is None or (isinstance(v, float) and not np.isfinite(v)):
        return "-"
    return f"{v:.{nd}f}"


def med_worst(values: list[float], nd: int = 2, high_is_bad: bool = True) -> str:
    """'median (worst)' over seeds."""
    v = np.asarray(values, float)
    worst = np.nanmax(v) if high_is_bad else np.nanmin(v)
    return f"{fmt(float(np.nanmedian(v)), nd)} ({fmt(float(worst), nd)})"


def claim1(label: str, ep: pd.DataFrame, s: dict) -> list[str]:
    """Fig. 1: ranking and speed of the learners."""
    J, J0, Jt = s["J_star"], s["J_initial"], s.get("J_tilde_star")
    rows = [
        f"**{label}** (J* = {J:.5g}, J_eval(theta0) = {J0:.5g} = {J0 / J:.2f} x J*"
        + (f", J~* = {Jt:.5g}" if Jt else "")
        + ")",
        "",
        "| learner | seeds | episodes | final J_eval/J* median (worst) | best J_eval/J* median "
        "(worst) | episodes to 10% / 5% / 2% of J* (per seed) | J~ of the last 100 episodes "
        "/ J~* (median over seeds) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name in s["learners"]:
        d = deployed_J_eval(ep[ep.learner == name])
        seeds = sorted(d.seed.unique())
        final, best, hits, tail = [], [], [], []
        for sd in seeds:
            g = d[d.seed == sd]
            ev = g["J_eval_incumbent"].dropna()
            final.append(g["J_eval_deployed"].iloc[-1] / J)
            best.append(ev.min() / J)
            firsts = [first_within(g, (1 + p) * J) for p in (0.10, 0.05, 0.02)]
            hits.append("/".join("-" if e is None else str(e) for e in firsts))
            if Jt:
                tail.append(np.nanmean(g["J_tilde"].iloc[-100:]) / Jt)
        n_ep = int(d.groupby("seed").episode.max().min()) + 1
        rows.append(
            f"| {name} | {len(seeds)} | {n_ep} | {med_worst(final)} | {med_worst(best)} | "
            f"{', '.join(hits)} | {fmt(float(np.median(tail))) if tail else '-'} |"
        )
    return rows


def claim2(label: str, ep: pd.DataFrame, s: dict) -> list[str]:
    """Fig. 2: the mean |A^w| per episode of MPC-RL and MOBO, by windows of episodes."""
    names = [n for n in ("mpc-rl", "mobo") if n in s["learners"]]
    n_ep = int(ep.episode.max()) + 1
    wins = [(a, min(b, n_ep)) for a, b in WINDOWS if a < n_ep]
    head = " | ".join(f"episodes {a + 1}-{b}" for a, b in wins)
    rows = [
        f"**{label}**: mean |A^w| per episode with a critic (an episode without one, which "
        "did not explore, has none), median over seeds of the window's median (per seed: "
        "min-max)",
        "",
        f"| learner | {head} |",
        "|---|" + "---|" * len(wins),
    ]
    meds: dict[str, list[float]] = {}
    for name in names:
        d = ep[ep.learner == name]
        d = d.assign(mean_abs_A=d["mean_abs_A"].where(d["critic_ok"]))  # no critic: no |A^w|
        cells = []
        for a, b in wins:
            w = d[(d.episode >= a) & (d.episode < b)].groupby("seed")["mean_abs_A"].median()
            meds.setdefault(name, []).append(float(w.median()))
            cells.append(f"{w.median():.3g} ({w.min():.3g}-{w.max():.3g})")
        rows.append(f"| {name} | " + " | ".join(cells) + " |")
    if len(names) == 2:
        ratio = [m / r for m, r in zip(meds["mobo"], meds["mpc-rl"])]
        rows.append("| mobo / mpc-rl | " + " | ".join(f"{r:.2f}" for r in ratio) + " |")
    return rows


def _outside(tr: pd.DataFrame, info: dict) -> list[str]:
    """Per state and input, the largest distance outside its limits, in its own units ("0":
    within the limits)."""
    cells = []
    for kind, names in (("x", info["state_names"]), ("u", info["input_names"])):
        lb, ub = info[f"{kind}_lb"], info[f"{kind}_ub"]
        for i, n in enumerate(names):
            v = tr[f"{kind}_{n}"].to_numpy(float)
            worst = 0.0
            if lb[i] is not None:
                worst = max(worst, float(np.nanmax(lb[i] - v, initial=0.0)))
            if ub[i] is not None:
                worst = max(worst, float(np.nanmax(v - ub[i], initial=0.0)))
            cells.append(f"{worst:.3g}" if worst > 0 else "0")
    return cells


def claim3(label: str, tr: pd.DataFrame, s: dict) -> list[str]:
    """Figs. 3-4: states and inputs of the stored episodes against their limits."""
    info = s["system_info"]
    names = list(info["state_names"]) + list(info["input_names"])
    limits = [f"{n} [{lo}, {hi}]" for n, lo, hi in zip(
        names, list(info["x_lb"]) + list(info["u_lb"]), list(info["x_ub"]) + list(info["u_ub"]))]  # fmt: skip
    rows = [
        f"**{label}**: the largest excursion of each state and input outside its limits in the "
        "stored episodes, in its own units (0 = within the limits)",
        "",
        "| episodes | seeds | starts x episodes | " + " | ".join(limits) + " |",
        "|---|---|---|" + "---|" * len(names),
    ]
    groups = [("theta0 (imperfect MPC), evaluation starts", tr[tr.phase == "initial"]),
              ("perfect-model MPC, evaluation starts", tr[tr.phase == "perfect"])]  # fmt: skip
    for name in s["learners"]:
        groups.append((f"{name}: learning episodes (every "
                       f"{s['settings']['records']['trajectory_every']}th)",
                       tr[(tr.phase == "learning") & (tr.learner == name)]))  # fmt: skip
        groups.append((f"{name}: final theta, evaluation starts",
                       tr[(tr.phase == "final") & (tr.learner == name)]))  # fmt: skip
    for what, g in groups:
        if g.empty:
            continue
        n_runs = g.groupby(["seed", "episode", "start"]).ngroups
        rows.append(f"| {what} | {g.seed.nunique()} | {n_runs} | "
                    + " | ".join(_outside(g, info)) + " |")  # fmt: skip
    return rows


def claim4(label: str, ep: pd.DataFrame, s: dict) -> list[str]:
    """Safety during learning: violations, failures and regressions of the deployed theta."""
    J, J0 = s["J_star"], s["J_initial"]
    rows = [
        f"**{label}**: per learning episode, the plant's summed constraint violation "
        "(median over seeds, worst seed in brackets)",
        "",
        "| learner | mean violation | max violation | episodes with a violation [%] | solver "
        "failures (all seeds) | evaluations with the deployed J_eval > J_eval(theta0) (all "
        "seeds) | worst deployed J_eval/J* median (worst) |",
        "|---|---|---|---|---|---|---|",
    ]
    for name in s["learners"]:
        d = deployed_J_eval(ep[ep.learner == name])
        by = d.groupby("seed")
        mean_v = by["violation"].mean().tolist()
        max_v = by["violation"].max().tolist()
        share = (by["violation"].apply(lambda v: float((v > 1e-9).mean())) * 100).tolist()
        fails = int(d["solver_failures"].sum())
        ev = d.dropna(subset=["J_eval_incumbent"])
        regress = int((ev["J_eval_incumbent"] > J0 * (1 + 1e-9)).sum())
        worst = (ev.groupby("seed")["J_eval_incumbent"].max() / J).tolist()
        rows.append(
            f"| {name} | {med_worst(mean_v)} | {med_worst(max_v, 1)} | {med_worst(share, 1)} | "
            f"{fails} | {regress} of {len(ev)} | {med_worst(worst)} |"
        )
    return rows


def main() -> None:
    """Print the tables for the run directories given."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--labels", nargs="*", default=None)
    a = ap.parse_args()
    labels = a.labels or [str(r) for r in a.runs]
    loaded = [(lab, *load(r)) for lab, r in zip(labels, a.runs)]
    for title, fn, uses in (
        ("Claim 1 (Fig. 1): ranking and speed", claim1, "ep"),
        ("Claim 2 (Fig. 2): |A^w| going to zero", claim2, "ep"),
        ("Claims 3 (Figs. 3-4): trajectories within the limits", claim3, "tr"),
        ("Claim 4: safety during learning", claim4, "ep"),
    ):
        print(f"### {title}\n")
        for lab, ep, tr, s in loaded:
            print("\n".join(fn(lab, ep if uses == "ep" else tr, s)) + "\n")


if __name__ == "__main__":
    main()
