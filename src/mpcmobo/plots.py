"""Figures 1-4 of the paper, drawn from a run's records only (no re-simulation).

Inputs: ``DIR/episodes.parquet``, ``DIR/trajectories.parquet`` and ``DIR/summary.json`` (J* and
the system's names, references and limits). Outputs: ``DIR/figures/fig{1..4}_*.{png,pdf}``.
With several seeds, per-episode curves are the median over seeds with the interquartile band.
Figures are plain :class:`matplotlib.figure.Figure` objects (no pyplot, no global backend): each is
saved with the Agg canvas that ``savefig`` picks for PNG and PDF.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from mpl_toolkits.mplot3d import Axes3D

from mpcmobo.bo.pareto import pareto_mask
from mpcmobo.learners.registry import LEARNER_SPECS

COLORS = {name: spec.color for name, spec in LEARNER_SPECS.items()}
LABELS = {name: spec.label for name, spec in LEARNER_SPECS.items()}
FIGURES = ("fig1_performance", "fig2_advantage_pareto", "fig3_states", "fig4_inputs")


def _band(df: pd.DataFrame, col: str) -> pd.DataFrame:
    """Median and quartiles over seeds of ``col`` per episode."""
    g = df.groupby("episode")[col]
    return pd.DataFrame({"med": g.median(), "q1": g.quantile(0.25), "q3": g.quantile(0.75)})


def _curve(
    ax: Axes, df: pd.DataFrame, col: str, color: str, label: str, n_seeds: int, **kw: Any
) -> None:
    b = _band(df, col).dropna(subset=["med"])
    ax.plot(b.index, b["med"], color=color, label=label, **kw)
    if n_seeds > 1:
        ax.fill_between(b.index, b["q1"], b["q3"], color=color, alpha=0.25, linewidth=0)


def _save(fig: Figure, out: Path, name: str) -> list[Path]:
    paths = []
    for ext in ("png", "pdf"):
        p = out / f"{name}.{ext}"
        fig.savefig(p, dpi=150, bbox_inches="tight")
        paths.append(p)
    return paths


def fig1(ep: pd.DataFrame, summary: dict, learners: list[str]) -> Figure:
    """Fig. 1: J tilde per episode and J_eval of the incumbent against J*, one panel per learner."""
    n = len(learners)
    fig = Figure(figsize=(8.5, 2.4 * n))
    axes = fig.subplots(n, 1, sharex=True, squeeze=False)
    J_star = summary["J_star"]
    for ax, name in zip(axes[:, 0], learners):
        d = ep[ep.learner == name]
        ns = d.seed.nunique()
        c = COLORS.get(name, "tab:orange")
        _curve(ax, d, "J_tilde", c, rf"$\tilde J$ {LABELS.get(name, name)}", ns, lw=1)
        ev = d[np.isfinite(d["J_eval_incumbent"])]
        if len(ev):
            _curve(ax, ev, "J_eval_incumbent", "black", r"$J_{eval}$ incumbent", ns, lw=1.2,
                   marker=".", ms=3)  # fmt: skip
        if J_star is not None:
            ax.axhline(J_star, color="tab:blue", ls="--", label=r"$J^\star$")
        elif summary.get("J_initial") is not None:  # no reference model: against theta0
            ax.axhline(summary["J_initial"], color="tab:green", ls=":",
                       label=r"$J(\theta_0)$ (no $J^\star$)")  # fmt: skip
        ax.set_ylabel(r"$\tilde J$")
        vals = d["J_tilde"].to_numpy(float)
        if np.any(np.isfinite(vals)) and np.nanmin(vals) > 0:
            ax.set_yscale("log")  # episode costs span orders of magnitude
        ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=7, borderaxespad=0)
    axes[-1, 0].set_xlabel("episode")
    fig.suptitle("Closed-loop performance per episode")
    return fig


def fig2(ep: pd.DataFrame, learners: list[str]) -> Figure:
    """Fig. 2: mean |A^w| per episode, and the MOBO observations with their Pareto front."""
    fig = Figure(figsize=(11, 4.2))
    _advantage_panel(fig.add_subplot(1, 2, 1), ep, learners)
    _pareto_panel(fig, fig.add_subplot(1, 2, 2, projection="3d"), ep, learners)
    return fig


def _advantage_panel(ax: Axes, ep: pd.DataFrame, learners: list[str]) -> None:
    """Mean |A^w| per episode of the critic-based learners (median and IQR over seeds)."""
    shown = [n for n in ("mpc-rl", "mobo") if n in learners] or learners
    for name in shown:
        d = ep[ep.learner == name]
        _curve(ax, d, "mean_abs_A", COLORS.get(name, "tab:orange"), LABELS.get(name, name),
               d.seed.nunique(), lw=1)  # fmt: skip
    ax.set_xlabel("episode")
    ax.set_ylabel(r"mean $|A^{w}|$")
    vals = ep.loc[ep.learner.isin(shown), "mean_abs_A"].to_numpy(float)
    if np.any(np.isfinite(vals)) and np.nanmin(vals) > 0:
        ax.set_yscale("log")
    ax.legend(fontsize=8)


def _pareto_panel(fig: Figure, ax3: Axes3D, ep: pd.DataFrame, learners: list[str]) -> None:
    """The observed objectives (f1, f2, f4, or f3 without f4) of the first seed of MOBO (else
    the last learner), with their Pareto front."""
    src = "mobo" if "mobo" in learners else learners[-1]
    d = ep[ep.learner == src]
    d = d[d.seed == d.seed.min()]
    cols = ["f1", "f2", "f4"] if np.isfinite(d["f4"]).any() else ["f1", "f2", "f3"]
    Y = d[cols].to_numpy(float)
    ok = np.all(np.isfinite(Y), axis=1)
    labels = list(cols)
    if ok.any():
        mask = pareto_mask(Y)
        Y = Y.copy()
        for j, c in enumerate(cols):  # objectives span decades: log axes (log10(1 + f) if f hits 0)
            v = Y[ok, j]
            if v.min() > 0:
                Y[:, j], labels[j] = np.log10(Y[:, j]), f"log10 {c}"
            elif v.min() >= 0:
                Y[:, j], labels[j] = np.log10(1.0 + Y[:, j]), f"log10(1+{c})"
        sc = ax3.scatter(*Y[ok & ~mask].T, c=d["episode"].to_numpy()[ok & ~mask], cmap="Greys",
                         s=8, alpha=0.7, label="observations")  # fmt: skip
        ax3.scatter(*Y[mask].T, marker="*", color="red", s=60, label="Pareto front")
        if (ok & ~mask).any():
            fig.colorbar(sc, ax=ax3, shrink=0.6, pad=0.1, label="episode")
        ax3.legend(fontsize=7)
    ax3.set_xlabel(labels[0])
    ax3.set_ylabel(labels[1])
    ax3.set_zlabel(labels[2])
    ax3.set_box_aspect(None, zoom=0.85)  # room for the z label
    ax3.set_title(f"Pareto front of the {LABELS.get(src, src)} observations", fontsize=9)


def _traj_figure(tr: pd.DataFrame, info: dict, learner: str, kind: str) -> Figure:
    names = info["state_names"] if kind == "x" else info["input_names"]
    ref = info["x_ref"] if kind == "x" else info["u_ref"]
    lb = info["x_lb"] if kind == "x" else info["u_lb"]
    ub = info["x_ub"] if kind == "x" else info["u_ub"]
    fig = Figure(figsize=(7, 2.2 * len(names)))
    axes = fig.subplots(len(names), 1, sharex=True, squeeze=False)
    initial = tr[(tr.phase == "initial")]
    learning = tr[(tr.phase == "learning") & (tr.learner == learner)]
    final = tr[(tr.phase == "final") & (tr.learner == learner)]
    for i, (ax, n) in enumerate(zip(axes[:, 0], names)):
        col = f"{kind}_{n}"
        for (_s, _e, _st), g in learning.groupby(["seed", "episode", "start"]):
            ax.plot(g.t, g[col], color="grey", lw=0.6, alpha=0.5)
        for _, g in initial.groupby("start"):
            ax.plot(g.t, g[col], color="tab:green", lw=1)
        _final_lines(ax, final, col)
        ax.axhline(ref[i], color="tab:orange", ls="--", lw=1)
        for lim in (lb[i], ub[i]):
            if lim is not None and np.isfinite(lim):
                ax.axhline(lim, color="red", ls="--", lw=1)
        ax.set_ylabel(n)
    handles = [
        Line2D([], [], color="tab:green", label="imperfect MPC"),
        Line2D([], [], color="grey", label="during learning"),
        Line2D([], [], color="tab:blue", label=f"learned MPC ({LABELS.get(learner, learner)})"),
        Line2D([], [], color="tab:orange", ls="--", label="reference"),
        Line2D([], [], color="red", ls="--", label="limits"),
    ]
    axes[0, 0].legend(handles=handles, fontsize=7, loc="upper right", ncol=2)
    axes[-1, 0].set_xlabel("time [min]" if info.get("name") == "cstr" else "time")
    fig.suptitle("States" if kind == "x" else "Control inputs")
    return fig


def _final_lines(ax: Axes, final: pd.DataFrame, col: str) -> None:
    """The final incumbent's evaluation episodes, one line per start (with several seeds: the
    median over seeds and the interquartile band)."""
    for _, g in final.groupby("start"):
        if final.seed.nunique() > 1:
            q = g.groupby("t")[col].quantile([0.25, 0.5, 0.75]).unstack()
            ax.plot(q.index, q[0.5], color="tab:blue", lw=1.2)
            ax.fill_between(q.index, q[0.25], q[0.75], color="tab:blue", alpha=0.25, lw=0)
        else:
            ax.plot(g.t, g[col], color="tab:blue", lw=1.2)


def make_figures(run_dir: str | Path, learner: str | None = None) -> list[Path]:
    """Write figures 1-4 (PNG and PDF) into ``run_dir/figures``; return the paths."""
    run_dir = Path(run_dir)
    ep = pd.read_parquet(run_dir / "episodes.parquet")
    tr = pd.read_parquet(run_dir / "trajectories.parquet")
    summary = json.loads((run_dir / "summary.json").read_text())
    info = summary["system_info"]
    present = list(dict.fromkeys(ep["learner"]))
    learners = [n for n in summary["learners"] if n in present] or present
    if not learners:
        raise ValueError(f"{run_dir} has no episodes to plot yet")
    if learner is None:
        learner = "mobo" if "mobo" in learners else learners[-1]
    elif learner not in learners:
        raise ValueError(f"learner '{learner}' is not in this run; allowed: {learners}")
    out = run_dir / "figures"
    out.mkdir(exist_ok=True)
    paths = _save(fig1(ep, summary, learners), out, FIGURES[0])
    paths += _save(fig2(ep, learners), out, FIGURES[1])
    paths += _save(_traj_figure(tr, info, learner, "x"), out, FIGURES[2])
    paths += _save(_traj_figure(tr, info, learner, "u"), out, FIGURES[3])
    return paths
