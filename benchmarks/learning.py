"""Learning benchmark: the learners on one system (the CSTR by default), several seeds.

Runs the real study runner (``mpcmobo.experiment.run_study``) and prints a markdown table:
episodes until the evaluated incumbent is within 5% and 2% of J*, the final J_eval/J*, the
worst J_eval/J* of the deployed theta over the run, the number of evaluations of the deployed
theta above J_eval(theta0) ("regressions"), constraint violation during learning (mean per
episode, and the largest episode per seed), and wall time per episode split into MPC and
learner. ``--system`` and ``--config`` (a settings file, e.g. learner options) are passed to
the study. While it runs, a progress line per job every 10 episodes goes to standard error.

Peer rows: ``--learners optuna-tpe optuna-gp`` runs Optuna's TPE and GP
samplers through the same study (``benchmarks/optuna_learners.py``; needs the ``bench`` extra,
``pip install -e ".[bench]"``). They are registered in this process only, so a run with them
uses one worker. The study's defaults identify the model first; the peers' published rows
tune the nominal model (``benchmarks/configs/noident.toml``).

    .venv/bin/python benchmarks/learning.py --episodes 50 --seeds 0 1 2 3 4 --out runs/bench-learning
    .venv/bin/python benchmarks/learning.py --config benchmarks/configs/noident.toml \
        --learners optuna-tpe optuna-gp --workers 1 --out runs/bench-optuna
    .venv/bin/python benchmarks/learning.py --table-only --out runs/a runs/b   # seeds pooled
    .venv/bin/python benchmarks/learning.py --compare "+id=runs/a" "=runs/b"
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd
from rich.console import Console

from mpcmobo.cli.progress import Lines
from mpcmobo.experiment.settings import load_settings
from mpcmobo.experiment.study import run_study


def _median_episodes(values: list) -> str:
    """Median of episode counts, a None (never reached) counting as infinitely many."""
    m = float(np.median([np.inf if v is None else v for v in values]))
    return "-" if not np.isfinite(m) else f"{m:g}"


def table(outs: list[Path], only_seeds: list[int] | None = None) -> str:
    """One markdown row per learner; with several run directories (same J*) the seeds of a
    learner are pooled, in the order given. ``only_seeds``: only these seeds (e.g. the
    complete seeds of a run that was stopped)."""
    summaries = [json.loads((out / "summary.json").read_text()) for out in outs]
    J_star = summaries[0]["J_star"]
    if any(not np.isclose(s["J_star"], J_star) for s in summaries):
        raise SystemExit("the run directories have different J*: their seeds cannot be pooled")
    df = pd.concat([pd.read_parquet(out / "episodes.parquet") for out in outs])
    lines = [
        f"J* = {J_star:.5g}, J_eval(theta0) = {summaries[0]['J_initial']:.5g} "
        f"(ratio {summaries[0]['J_initial'] / J_star:.2f})",
        "",
        "| learner | seeds | episodes to 5% (median, per seed) | episodes to 2% (median, per seed) "
        "| final J_eval/J* (median, per seed) | worst deployed J_eval/J* (per seed) "
        "| regressions | violation per episode (mean; max per seed) "
        "| MPC s/episode | learner s/episode |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    names = list(dict.fromkeys(n for s in summaries for n in s["learners"]))
    for name in names:
        per = [
            s["learners"][name]["per_seed"][k]
            for s in summaries
            if name in s["learners"]
            for k in sorted(s["learners"][name]["per_seed"], key=int)
            if only_seeds is None or int(k) in only_seeds
        ]
        to5 = [p["episodes_to_5pct"] for p in per]
        to2 = [p["episodes_to_2pct"] for p in per]
        ratio = [p["J_final"] / J_star if p["J_final"] is not None else np.nan for p in per]
        d = df[df["learner"] == name]
        if only_seeds is not None:
            d = d[d["seed"].isin(only_seeds)]
        J0 = summaries[0]["J_initial"]
        seeds = [
            int(k)
            for s in summaries
            if name in s["learners"]
            for k in sorted(s["learners"][name]["per_seed"], key=int)
            if only_seeds is None or int(k) in only_seeds
        ]
        worst, regress, vmax = [], 0, []
        for seed in seeds:
            ds = d[d["seed"] == seed]
            ev = ds["J_eval_incumbent"].dropna()
            worst.append(ev.max() / J_star if len(ev) else np.nan)
            # evaluations of the deployed theta above J_eval(theta0) (1e-9 relative slack)
            regress += int(np.sum(ev > J0 * (1 + 1e-9)))
            vmax.append(ds["violation"].max())

        def fmt(v):
            return "-" if v is None else str(v)

        lines.append(
            f"| {name} | {len(per)} | {_median_episodes(to5)} ({', '.join(map(fmt, to5))}) "
            f"| {_median_episodes(to2)} ({', '.join(map(fmt, to2))}) "
            f"| {np.nanmedian(ratio):.3f} ({', '.join(f'{r:.2f}' for r in ratio)}) "
            f"| {', '.join(f'{w:.2f}' for w in worst)} | {regress} "
            f"| {d['violation'].mean():.3g}; {', '.join(f'{v:.3g}' for v in vmax)} "
            f"| {d['mpc_time_s'].mean():.2f} "
            f"| {d['learner_time_s'].mean():.2f} |"
        )
    return "\n".join(lines)


def _first_deployment(d: pd.DataFrame) -> int:
    """The first episode after which the deployed theta is not the first one (len: never)."""
    first = np.asarray(d["incumbent"].iloc[0], float)
    moved = [not np.allclose(inc, first, rtol=0, atol=1e-12) for inc in d["incumbent"]]
    return int(np.argmax(moved)) if any(moved) else len(d)


def plant_table(outs: list[Path], only_seeds: list[int] | None = None) -> str:
    """What tuning cost the plant, one row per learner (seeds pooled over ``outs``): the
    cumulative plant cost of the episodes (the sum of their mean stage costs; median and worst
    over seeds), its ratio to ``identify``'s of the same seed (median, worst), the cumulative
    excess over the deployed controller from the same starts, the worst exploring episode after
    the first deployment as a multiple of the deployed controller's cost from its start with
    its noise (plant cost / (plant cost - excess)), the candidates refused by the exploration
    budget and the seeds whose tuning converged (stopped exploring) with the median episode."""
    df = pd.concat([pd.read_parquet(out / "episodes.parquet") for out in outs])
    if only_seeds is not None:
        df = df[df["seed"].isin(only_seeds)]
    total = df.groupby(["learner", "seed"])["plant_cost"].sum()
    ident = total.get("identify") if "identify" in total.index.get_level_values(0) else None
    lines = [
        "| learner | seeds | plant cost, sum over episodes (median, worst) | / identify's "
        "(median, worst) | excess over the deployed (median, worst) | worst exploring "
        "episode / deployed, after the first deployment | refused candidates | converged "
        "(seeds, median episode) |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name in dict.fromkeys(df["learner"]):
        d = df[df["learner"] == name]
        t = total[name]
        rel = (t / ident).dropna().to_numpy() if ident is not None else np.array([])
        excess = d.groupby("seed")["excess_cost"].sum()
        worst, conv = [], []
        for _, ds in d.groupby("seed"):
            ds = ds.sort_values("episode")
            after = ds.iloc[_first_deployment(ds) + 1 :]
            e = after["excess_cost"].to_numpy(float)
            c = after["plant_cost"].to_numpy(float)
            ok = np.isfinite(e) & np.isfinite(c) & (e != 0)
            worst.append(float(np.max(c[ok] / (c[ok] - e[ok]))) if ok.any() else 1.0)
            # converged: the first episode without a prediction in a run that predicts
            stops = ds["episode"][ds["predicted_cost"].isna() & (ds["episode"] > 0)]
            if ds["predicted_cost"].notna().any() and len(stops):
                conv.append(int(stops.iloc[0]))
        refused = int((d["refused"] != "").sum()) if "refused" in d else 0
        rel_col = f"{np.median(rel):.3f}, {rel.max():.3f}" if len(rel) else "-"
        conv_col = f"{len(conv)}, {np.median(conv):g}" if conv else "0"
        lines.append(
            f"| {name} | {len(t)} | {t.median():.4g}, {t.max():.4g} | {rel_col} "
            f"| {excess.median():.4g}, {excess.max():.4g} | {max(worst):.2f} | {refused} "
            f"| {conv_col} |"
        )
    return "\n".join(lines)


def compare(runs: list[tuple[str, Path]]) -> str:
    """One compact row per (label, learner) of several run directories of one system (same
    J*), not pooled, and theta0's: the final J_eval/J* (median, worst seed), the final thetas
    on fresh starts where the directory holds ``recheck.json`` (``benchmarks/recheck.py --thetas
    final --json DIR/recheck.json``), the evaluations above theta0 and the seeds with them, the
    violation per episode (a plant that diverged or ran away was stopped: the steps it ran)
    and the failed episodes (those without a result: f1 NaN), the episodes to 2% of J*
    (median)."""
    first = json.loads((runs[0][1] / "summary.json").read_text())
    J_star, J0 = first["J_star"], first["J_initial"]
    lines = [
        "| learner | seeds | final J_eval/J* (median, worst) | on 100 fresh starts (median, worst) "
        "| evaluations above theta0 (seeds) | violation per episode | failed episodes "
        "| episodes to 2% |",
        "|---|---|---|---|---|---|---|---|",
        f"| theta0 | | {J0 / J_star:.3f} | | | | | |",
    ]
    for label, out in runs:
        summary = json.loads((out / "summary.json").read_text())
        if not np.isclose(summary["J_star"], J_star):
            raise SystemExit(f"{out} has another J* than {runs[0][1]}")
        df = pd.read_parquet(out / "episodes.parquet")
        fresh: dict[tuple[str, int], float] = {}
        if (out / "recheck.json").exists():
            for r in json.loads((out / "recheck.json").read_text()):
                if r["theta"] == "final":
                    fresh[(r["learner"], int(r["seed"]))] = r["J_fresh_ratio"]
        for name, s in summary["learners"].items():
            per = s["per_seed"]
            ratio = np.array([per[k]["J_final"] / J_star for k in sorted(per, key=int)])
            d = df[df["learner"] == name]
            ev = d.dropna(subset=["J_eval_incumbent"])
            above = ev[ev["J_eval_incumbent"] > J0 * (1 + 1e-9)]
            f = np.array([v for (n, _), v in fresh.items() if n == name])
            fresh_col = f"{np.median(f):.3f}, {f.max():.3f}" if len(f) else "-"
            to2 = _median_episodes([per[k]["episodes_to_2pct"] for k in per])
            lines.append(
                f"| {name}{label} | {len(per)} | {np.median(ratio):.3f}, {ratio.max():.3f} "
                f"| {fresh_col} | {len(above)} ({above['seed'].nunique()}) "
                f"| {d['violation'].mean():.3g} | {int(d['f1'].isna().sum())} | {to2} |"
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
    ap.add_argument("--system", default=None, help="registered system (default: the settings')")
    ap.add_argument(
        "--config", type=Path, default=None, help="TOML settings file (e.g. learner options)"
    )
    ap.add_argument(
        "--out",
        type=Path,
        nargs="+",
        default=[Path("runs/bench-learning")],
        help="run directory; with --table-only, several directories pool their seeds",
    )
    ap.add_argument("--table-only", action="store_true", help="only print the table of --out")
    ap.add_argument(
        "--compare",
        nargs="+",
        default=None,
        metavar="LABEL=DIR",
        help="print the compact table of these run directories (a label per directory, added "
        "to its learners' names; an empty label: LABEL is empty before '=')",
    )
    ap.add_argument(
        "--only-seeds", type=int, nargs="+", default=None, help="table: only these seeds"
    )
    ap.add_argument(
        "--budget",
        type=float,
        default=None,
        help="the exploration budget ([exploration] budget; inf: none; default: the settings')",
    )
    args = ap.parse_args()
    if args.compare:
        pairs = [item.partition("=") for item in args.compare]
        print(compare([(label, Path(d)) for label, _, d in pairs]))
        return
    if any(name.startswith("optuna-") for name in args.learners):
        from optuna_learners import register  # benchmarks/ is on sys.path when run as a script

        register()
        if args.workers != 1 and not args.table_only:
            raise SystemExit("the optuna-* learners run with --workers 1 (this process only)")
    if not args.table_only:
        if len(args.out) != 1:
            raise SystemExit("one --out directory per run (several only with --table-only)")
        settings = load_settings(
            args.config,
            system={"name": args.system} if args.system else None,
            learners=args.learners,
            episodes=args.episodes,
            seeds=args.seeds,
            workers=args.workers,
            start_mode=args.start_mode,
            evaluation={"eval_every": args.eval_every},
            **({} if args.budget is None else {"exploration": {"budget": args.budget}}),
        )
        resume = (args.out[0] / "config.toml").exists()
        progress = Lines(Console(stderr=True), every=10)
        run_study(None if resume else settings, args.out[0], resume=resume, progress=progress)
    print(table(args.out, args.only_seeds))
    print()
    print(plant_table(args.out, args.only_seeds))


if __name__ == "__main__":
    main()
