"""Recheck a run's deployed thetas on many fresh initial states.

J_eval is the mean cost over ``evaluation.n_starts`` (10) fixed starts, and on the CSTR a few
starts dominate that mean: a theta can win on most starts and still lose in J_eval because of
one, or the other way round. This script re-evaluates, for every learner and seed of one or
more run directories, theta0 (on each job's own MPC), the final deployed theta and the worst
deployed theta (the one with the largest J_eval over the run) on ``--starts`` fresh initial
states drawn from the system's initial-state distribution with their own seed (never the
evaluation starts, never fed back to a learner), with the same MPC options and plant as the
run. It prints, per theta,
its mean cost over the fresh starts relative to J* on the same starts, the paired difference
from theta0's mean with its standard error over the starts, and on how many starts it beats
theta0; "regression" is a mean above theta0's. A theta that runs the plant away from a fresh
start has an infinite mean there (a regression). ``--thetas final`` rechecks the final thetas
only; ``--summary`` prints one row per learner instead (the median and the worst seed of the
final theta on the fresh starts, the seeds whose final theta is worse than theta0 there, and,
with ``identify`` among the runs, the seeds whose final theta ends above ``identify``'s on
either set of starts).

    .venv/bin/python benchmarks/recheck.py --out runs/a --starts 100 --json runs/a/recheck.json
    .venv/bin/python benchmarks/recheck.py --out runs/a --thetas final --summary
    .venv/bin/python benchmarks/recheck.py --from-json runs/a/recheck.json runs/b/recheck.json --summary
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

from mpcmobo.experiment.build import build_system, identified_parameters
from mpcmobo.experiment.evaluation import Evaluator, make_evaluator
from mpcmobo.experiment.settings import load_settings
from mpcmobo.rl.objectives import mean_stage_cost

RECHECK_SEED = 4242  # the fresh starts' seed: apart from the evaluation's (2025)


def _thetas(df: pd.DataFrame, which: tuple[str, ...]) -> dict[str, tuple[np.ndarray, float]]:
    """The final and the worst deployed theta of one job's rows, each with its J_eval."""
    rows = df.sort_values("episode")
    J = rows["J_eval_incumbent"].to_numpy(float)
    picks = {"final": len(J) - 1, "worst": int(np.argmax(np.where(np.isnan(J), -np.inf, J)))}
    return {
        k: (np.asarray(rows["incumbent"].iloc[i], float), float(J[i]))
        for k, i in picks.items()
        if k in which
    }


def recheck(
    out: Path,
    starts: int,
    seed: int,
    only_seeds: list[int] | None,
    which: tuple[str, ...] = ("final", "worst"),
) -> list[dict]:
    """The recheck rows of one run directory (one per learner, seed and theta)."""
    settings = load_settings(out / "config.toml")
    system = build_system(settings)
    # a job's MPC is the study's with the parameters it identifies in theta: one evaluator,
    # one theta0 and one cache per set of identified parameters (() is the study's own)
    evs: dict[tuple[str, ...], Evaluator] = {
        (): make_evaluator(settings, system, n_starts=starts, seed=seed)
    }
    summary = json.loads((out / "summary.json").read_text())
    df = pd.read_parquet(out / "episodes.parquet")

    def mpc_of(learner: str | None) -> tuple[str, ...]:
        key = identified_parameters(settings, system, learner)
        if key not in evs:
            evs[key] = make_evaluator(
                settings, build_system(settings, learner), n_starts=starts, seed=seed
            )
        return key

    def costs(
        theta: np.ndarray | None, mpc: tuple[str, ...] = (), model: str = "imperfect"
    ) -> np.ndarray:
        try:
            return np.array([mean_stage_cost(r) for r in evs[mpc].episodes(theta, model)])
        except FloatingPointError:
            if theta is None:  # J*'s or theta0's MPC: nothing to compare with
                raise
            return np.full(starts, np.inf)  # the theta runs the plant away from a start

    # one cache of costs per MPC and theta (None: theta0, on each job's own MPC: identified
    # parameters in theta make another problem of the same MPC, and a hot start tells them apart)
    cache: dict[tuple[tuple[str, ...], bytes | None], np.ndarray] = {}

    def cached(theta: np.ndarray | None, mpc: tuple[str, ...]) -> np.ndarray:
        key = (mpc, None if theta is None else theta.tobytes())
        if key not in cache:
            cache[key] = costs(theta, mpc)
        return cache[key]

    ref = costs(None, model="perfect") if evs[()].has_J_star else None
    J_star = float(ref.mean()) if ref is not None else float(cached(None, ()).mean())
    rows: list[dict] = []
    for (learner, s), job in df.groupby(["learner", "seed"], sort=True):
        if only_seeds is not None and int(s) not in only_seeds:
            continue
        mpc = mpc_of(learner)
        c0 = cached(None, mpc)
        for name, (theta, J_eval) in _thetas(job, which).items():
            c = cached(theta, mpc)
            rows.append(
                {
                    "run": out.name,
                    "learner": learner,
                    "seed": int(s),
                    "theta": name,
                    "J_eval_ratio": J_eval / summary["J_star"],
                    "J_fresh_ratio": float(c.mean()) / J_star,
                    "J0_fresh_ratio": float(c0.mean()) / J_star,
                    "wins": int(np.sum(c < c0)),
                    # the paired difference of the means and its standard error over the starts
                    "diff_ratio": float((c - c0).mean()) / J_star,
                    "diff_se_ratio": float((c - c0).std(ddof=1) / np.sqrt(len(c))) / J_star
                    if len(c) > 1
                    else float("nan"),
                    "starts": int(len(c)),
                    "regression": bool(c.mean() > c0.mean()),
                }
            )
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, nargs="+", default=[], help="run directories")
    ap.add_argument(
        "--from-json",
        type=Path,
        nargs="+",
        default=[],
        help="rows written by --json before: summarised with --summary, not evaluated again",
    )
    ap.add_argument("--starts", type=int, default=100, help="fresh initial states (default 100)")
    ap.add_argument("--seed", type=int, default=RECHECK_SEED, help="their seed")
    ap.add_argument("--only-seeds", type=int, nargs="+", default=None)
    ap.add_argument("--json", type=Path, default=None, help="also write the rows here")
    ap.add_argument("--thetas", nargs="+", default=["final", "worst"], choices=["final", "worst"])
    ap.add_argument("--summary", action="store_true", help="one row per learner")
    args = ap.parse_args()
    which = tuple(args.thetas)
    if not args.out and not args.from_json:
        ap.error("give run directories (--out) or rows written before (--from-json)")
    rows = [r for path in args.from_json for r in json.loads(path.read_text())]
    rows += [
        r for out in args.out for r in recheck(out, args.starts, args.seed, args.only_seeds, which)
    ]
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=1))
    if args.summary:
        print(summary_table(rows, args.starts))
        return
    print(
        "| run | learner | seed | theta | J_eval/J* (10 evaluation starts) "
        f"| J/J* on {args.starts} fresh starts | theta0 there | difference (SE) "
        "| wins over theta0 | regression |"
    )
    print("|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(
            f"| {r['run']} | {r['learner']} | {r['seed']} | {r['theta']} | {r['J_eval_ratio']:.2f} "
            f"| {r['J_fresh_ratio']:.2f} | {r['J0_fresh_ratio']:.2f} "
            f"| {r['diff_ratio']:+.2f} ({r['diff_se_ratio']:.2f}) | {r['wins']}/{r['starts']} "
            f"| {'yes' if r['regression'] else 'no'} |"
        )


ABOVE = 5e-4  # "above identify": a final theta's J more than 0.05% above identify's, same seed


def _finals(rows: list[dict]) -> list[dict]:
    """The final thetas' rows, each with its ``label``: the learner, and its run's name where
    the learner is in several runs (with and without identification, say)."""
    finals = [r for r in rows if r["theta"] == "final"]
    runs: dict[str, set[str]] = {}
    for r in finals:
        runs.setdefault(r["learner"], set()).add(r.get("run", ""))
    return [
        dict(
            r,
            label=r["learner"] if len(runs[r["learner"]]) == 1 else f"{r['learner']} ({r['run']})",
        )
        for r in finals
    ]


def above_identify(rows: list[dict]) -> dict[str, str]:
    """Per learner (not ``identify``; :func:`_finals`' label), the seeds whose final theta ends
    above ``identify``'s final theta of the same seed by more than ``ABOVE``, on the evaluation
    starts ("eval") or on the fresh starts ("fresh"), each with its excess in percent: "none",
    or "" where no ``identify`` row of that seed is among ``rows``."""
    finals = _finals(rows)
    ident = {r["seed"]: r for r in finals if r["learner"] == "identify"}
    out: dict[str, str] = {}
    for learner in dict.fromkeys(r["label"] for r in finals if r["learner"] != "identify"):
        rs = [r for r in finals if r["label"] == learner and r["seed"] in ident]
        if not rs:
            out[learner] = ""
            continue
        cells = []
        for r in rs:
            i = ident[r["seed"]]
            for key, where in (("J_eval_ratio", "eval"), ("J_fresh_ratio", "fresh")):
                excess = r[key] / i[key] - 1
                if excess > ABOVE:
                    cells.append(f"{r['seed']} ({where} +{100 * excess:.1f}%)")
        out[learner] = ", ".join(cells) or "none"
    return out


def summary_table(rows: list[dict], starts: int) -> str:
    """One markdown row per learner: its final thetas on the fresh starts, and, with
    ``identify`` among the rows, the seeds that end above it (:func:`above_identify`)."""
    above = above_identify(rows)
    lines = [
        f"| learner | seeds | final J/J* on {starts} fresh starts (median, worst) "
        "| theta0 there | seeds worse than theta0 there | seeds above `identify` |",
        "|---|---|---|---|---|---|",
    ]
    finals = _finals(rows)
    for learner in dict.fromkeys(r["label"] for r in finals):
        rs = [r for r in finals if r["label"] == learner]
        v = np.array([r["J_fresh_ratio"] for r in rs])
        worse = [str(r["seed"]) for r in rs if r["regression"]]
        lines.append(
            f"| {learner} | {len(rs)} | {np.median(v):.3f}, {v.max():.3f} "
            f"| {rs[0]['J0_fresh_ratio']:.3f} | {', '.join(worse) or 'none'} "
            f"| {above.get(learner, '')} |"
        )
    return "\n".join(lines)


if __name__ == "__main__":
    main()
