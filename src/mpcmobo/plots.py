"""Figures 1-4 of the paper, drawn from a run's records only (no re-simulation).

Inputs: ``DIR/episodes.parquet``, ``DIR/trajectories.parquet`` and ``DIR/summary.json`` (J* and
the system's names, references and limits). Outputs: ``DIR/figures/fig{1..4}_*.{png,pdf}``.
With several seeds, per-episode curves are the median over seeds with the interquartile band,
and the legend says how many seeds; a run with one seed draws single lines.

Fig. 1 compares like with like: the training curve J~ (f1, eq. cl_perf: discounted,
with exploration, on the training starts) is drawn against J~* (the same f1 of the perfect-model
MPC on the same training starts with the same noise, ``summary.json`` ``J_tilde_star``; with
random starts on the first training starts alone, as its legend says), and
J_eval of the deployed theta (undiscounted, no exploration, on the fixed evaluation starts)
against J* (the same mean stage cost of the perfect-model MPC on the same starts). Per-episode
J~ is drawn faint, and on top its mean over as many episodes as make J~* of a seed (one cycle
of the starts; with random starts ``evaluation.n_starts``). A run made before J~* existed says
so in the panel instead of drawing an unlike reference.
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
from matplotlib.ticker import FuncFormatter, MaxNLocator

if TYPE_CHECKING:
    from matplotlib.axes import Axes
    from mpl_toolkits.mplot3d import Axes3D

from mpcmobo.bo.pareto import pareto_mask
from mpcmobo.learners.registry import LEARNER_SPECS

COLORS = {name: spec.color for name, spec in LEARNER_SPECS.items()}
LABELS = {name: spec.label for name, spec in LEARNER_SPECS.items()}
FIGURES = ("fig1_performance", "fig2_advantage_pareto", "fig3_states", "fig4_inputs")
IDENTIFIED = "fig5_identified"  # drawn when a learner identifies the model


def seeds_note(n_seeds: int) -> str:
    """What a curve of ``n_seeds`` seeds shows, for its legend entry."""
    return "1 seed" if n_seeds == 1 else f"median, IQR of {n_seeds} seeds"


def _band(df: pd.DataFrame, col: str) -> pd.DataFrame:
    """Median and quartiles over seeds of ``col`` per episode."""
    g = df.groupby("episode")[col]
    return pd.DataFrame({"med": g.median(), "q1": g.quantile(0.25), "q3": g.quantile(0.75)})


def _curve(
    ax: Axes,
    df: pd.DataFrame,
    col: str,
    color: str,
    label: str,
    n_seeds: int,
    band: bool = True,
    **kw: Any,
) -> None:
    """The median over seeds of ``col`` per episode, and with several seeds its interquartile
    band (unless ``band`` is False)."""
    b = _band(df, col).dropna(subset=["med"])
    if len(b) == 1:  # one episode: a point, which a line alone does not draw
        kw = {"marker": "o", **kw}
    ax.plot(b.index, b["med"], color=color, label=label, **kw)
    if n_seeds > 1 and band:
        step: dict[str, Any] = {"step": "post"} if kw.get("drawstyle") == "steps-post" else {}
        ax.fill_between(b.index, b["q1"], b["q3"], color=color, alpha=0.25, linewidth=0, **step)


def moving_mean(df: pd.DataFrame, col: str, window: int) -> pd.DataFrame:
    """``df`` (one learner) with ``{col}_mean``: per seed, the mean of ``col`` over the last
    ``window`` episodes (NaN for the first ``window - 1`` episodes and over a window holding a
    NaN episode): with cycled starts one mean covers every start once, as J~* does."""
    d = df.sort_values(["seed", "episode"]).copy()
    d[f"{col}_mean"] = d.groupby("seed")[col].transform(
        lambda v: v.rolling(window, min_periods=window).mean()
    )
    return d


def deployed_J_eval(df: pd.DataFrame) -> pd.DataFrame:
    """``df`` (one learner) with ``J_eval_deployed``: per seed, J_eval of the last evaluated
    incumbent at every episode (the evaluation schedule evaluates at episode 0, so every
    episode has one), so that the median over seeds is taken over all seeds at every episode."""
    d = df.sort_values(["seed", "episode"]).copy()
    d["J_eval_deployed"] = d.groupby("seed")["J_eval_incumbent"].ffill()
    return d


def reference_window(summary: dict) -> int:
    """The number of episodes of J~* per seed, also the window of the moving means: from the
    summary, or for a run without J~* from its settings (as
    :func:`mpcmobo.experiment.training_reference.training_reference_episodes` chooses it)."""
    n = summary.get("J_tilde_star_episodes")
    if n:
        return int(n)
    st = summary.get("settings", {})
    if st.get("start_mode", "cycle") == "cycle":
        return int(st.get("n_cycle_starts", 6))
    return int(st.get("evaluation", {}).get("n_starts", 10))


def _save(fig: Figure, out: Path, name: str, note: str = "") -> list[Path]:
    """``fig`` as ``name``.png and .pdf in ``out``, with ``note`` (a partial run's) at its
    foot."""
    if note:
        fig.text(0.01, 0.0, note, fontsize=8, color="0.3", va="top", wrap=True)
    paths = []
    for ext in ("png", "pdf"):
        p = out / f"{name}.{ext}"
        fig.savefig(p, dpi=150, bbox_inches="tight")
        paths.append(p)
    return paths


def _tick(y: float, _pos: Any = None) -> str:
    """A log axis tick as a plain number, labelled at mantissas 1, 2 and 5 only."""
    if not np.isfinite(y) or y <= 0:
        return ""
    mantissa = y / 10 ** np.floor(np.log10(y) + 1e-9)
    if not any(np.isclose(mantissa, m) for m in (1, 2, 5)):
        return ""
    if y >= 1e6 or y < 1e-3:
        return f"{y:.0e}".replace("e+0", "e").replace("e-0", "e-")
    return f"{y:.0f}" if y >= 1 else f"{y:.2g}"


def _log_if_positive(ax: Axes, values: Any) -> None:
    """A log y axis if the values are positive and span more than a factor of 10 (episode costs
    span orders of magnitude), its ticks as plain numbers: the decades, and 2 and 5 x 10^k
    between them when the drawn axis spans less than a factor of 100."""
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    if len(v) and v.min() > 0 and v.max() > 10 * v.min():
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(FuncFormatter(_tick))

        def minor(
            y: float, pos: Any = None
        ) -> str:  # 2 and 5 x 10^k only when the drawn axis spans < 100
            lo, hi = ax.get_ylim()
            return _tick(y) if 0 < lo and hi < 100 * lo else ""

        ax.yaxis.set_minor_formatter(FuncFormatter(minor))


def _note(ax: Axes, text: str) -> None:
    ax.text(
        0.5,
        0.04,
        text,
        transform=ax.transAxes,
        ha="center",
        va="bottom",
        fontsize=8,
        color="tab:blue",
        bbox={"facecolor": "white", "edgecolor": "tab:blue"},
    )


def fig1(ep: pd.DataFrame, summary: dict, learners: list[str]) -> Figure:
    """Fig. 1, like with like: per learner, the training curve J~ against J~* (left) and
    J_eval of the deployed theta against J* (right); each pair is computed the same way."""
    n = len(learners)
    fig = Figure(figsize=(12, 2.7 * n + 0.4), layout="constrained")
    axes = fig.subplots(n, 2, sharex=True, squeeze=False)
    for (ax, ax_eval), name in zip(axes, learners):
        d = ep[ep.learner == name]
        _training_panel(ax, d, name, summary)
        _evaluation_panel(ax_eval, d, name, summary)
    n_eval = summary.get("settings", {}).get("evaluation", {}).get("n_starts")
    starts = f"{n_eval} fixed evaluation starts" if n_eval else "fixed evaluation starts"
    axes[0, 0].set_title(
        r"training: $\tilde J$ = f1 (discounted, with exploration, "
        "training starts)",
        fontsize=9,
    )
    axes[0, 1].set_title(
        rf"evaluation: $J_{{eval}}$ (undiscounted, no exploration, {starts})", fontsize=9
    )
    for ax in axes[-1]:
        ax.set_xlabel("episode")
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    fig.suptitle("Closed-loop performance per episode, each curve against its own reference")
    return fig


def _training_panel(ax: Axes, d: pd.DataFrame, name: str, summary: dict) -> None:
    """Fig. 1, left, for the learner ``name`` (its rows ``d``): J~ per episode and its moving
    mean against J~*, the perfect-model MPC from the same starts with the same noise."""
    K = reference_window(summary)
    Jt_star = summary.get("J_tilde_star")
    per_seed = [v for v in (summary.get("J_tilde_star_per_seed") or {}).values() if v is not None]
    ns = d.seed.nunique()
    c, label = COLORS.get(name, "tab:orange"), LABELS.get(name, name)
    each = "per episode" + (" (median)" if ns > 1 else "")
    _curve(ax, d, "J_tilde", c, each, ns, band=False, lw=0.6, alpha=0.4)
    m = moving_mean(d, "J_tilde", K)
    none = "" if m["J_tilde_mean"].notna().any() else ": none yet"
    _curve(
        ax,
        m,
        "J_tilde_mean",
        c,
        f"{label}: mean of {K} episodes ({seeds_note(ns)}){none}",
        ns,
        lw=1.6,
    )
    if Jt_star is not None:
        ax.axhline(
            Jt_star,
            color="tab:blue",
            ls="--",
            lw=1.2,
            label=_training_reference_label(summary, K)
            + (f" (median of {len(per_seed)} seeds)" if len(per_seed) > 1 else ""),
        )
        if len(per_seed) > 1:
            q1, q3 = np.quantile(per_seed, [0.25, 0.75])
            ax.axhspan(q1, q3, color="tab:blue", alpha=0.12, lw=0)
    else:
        _note(ax, "no like-for-like reference in this run")
    _log_if_positive(ax, np.r_[d["J_tilde"].to_numpy(float), per_seed])
    ax.set_ylabel(rf"{label}: $\tilde J$")
    ax.legend(loc="best", fontsize=7, framealpha=0.85)


def _training_reference_label(summary: dict, K: int) -> str:
    """What J~* of Fig. 1 is: with cycled starts the perfect-model MPC from the starts every
    cycle repeats; with random starts from the first ``K`` training starts alone, which the
    later episodes do not share."""
    if summary.get("settings", {}).get("start_mode", "cycle") == "cycle":
        return r"$\tilde J^\star$: perfect-model MPC, same starts and noise"
    return rf"$\tilde J^\star$: perfect-model MPC, the first {K} starts only (random starts)"


def _evaluation_panel(ax_eval: Axes, d: pd.DataFrame, name: str, summary: dict) -> None:
    """Fig. 1, right, for the learner ``name`` (its rows ``d``): J_eval of the deployed theta
    against J* (or, without J*, against J_eval(theta0))."""
    J_star = summary.get("J_star")
    ns = d.seed.nunique()
    c, label = COLORS.get(name, "tab:orange"), LABELS.get(name, name)
    e = deployed_J_eval(d)
    _curve(
        ax_eval,
        e,
        "J_eval_deployed",
        c,
        rf"{label}: $J_{{eval}}$ of the deployed $\theta$ ({seeds_note(ns)})",
        ns,
        lw=1.6,
        drawstyle="steps-post",
    )
    if ns == 1:  # the evaluated episodes
        ev = e[np.isfinite(e["J_eval_incumbent"])]
        ax_eval.plot(ev.episode, ev.J_eval_incumbent, ls="none", marker=".", ms=4, color=c)
    if J_star is not None:
        ax_eval.axhline(
            J_star,
            color="tab:blue",
            ls="--",
            lw=1.2,
            label=r"$J^\star$: perfect-model MPC, same starts",
        )
    elif summary.get("J_initial") is not None:  # no reference model: against theta0
        ax_eval.axhline(
            summary["J_initial"],
            color="tab:green",
            ls=":",
            lw=1.2,
            label=r"$J(\theta_0)$ (no $J^\star$ in this run)",
        )
    else:
        _note(ax_eval, "no J* in this run")
    _log_if_positive(ax_eval, np.r_[e["J_eval_deployed"].to_numpy(float), J_star or np.nan])
    ax_eval.set_ylabel(rf"{label}: $J_{{eval}}$")
    ax_eval.legend(loc="best", fontsize=7, framealpha=0.85)


def fig2(ep: pd.DataFrame, learners: list[str], window: int = 1) -> Figure:
    """Fig. 2: mean |A^w| per episode (and its mean over ``window`` episodes), and the MOBO
    observations with their Pareto front."""
    fig = Figure(figsize=(12, 4.4), layout="constrained")
    _advantage_panel(fig.add_subplot(1, 2, 1), ep, learners, window)
    _pareto_panel(fig, fig.add_subplot(1, 2, 2, projection="3d"), ep, learners)
    return fig


def _advantage_panel(ax: Axes, ep: pd.DataFrame, learners: list[str], window: int = 1) -> None:
    """Mean |A^w| per episode of the critic-based learners (median and IQR over seeds); with
    ``window > 1`` the per-episode median is drawn faint and the mean over ``window`` episodes
    (median and IQR over seeds) on top."""
    shown = [n for n in ("mpc-rl", "mobo") if n in learners] or learners
    for name in shown:
        d = ep[ep.learner == name]
        # an episode without a critic (one that did not explore) has no advantage, not zero
        d = d.assign(mean_abs_A=d["mean_abs_A"].where(d["critic_ok"]))
        ns, c, label = d.seed.nunique(), COLORS.get(name, "tab:orange"), LABELS.get(name, name)
        if window > 1:
            each = "per episode" + (" (median)" if ns > 1 else "")
            _curve(ax, d, "mean_abs_A", c, f"{label}: {each}", ns, band=False, lw=0.6, alpha=0.4)
            m = moving_mean(d, "mean_abs_A", window)
            none = "" if m["mean_abs_A_mean"].notna().any() else ": none yet"
            _curve(
                ax,
                m,
                "mean_abs_A_mean",
                c,
                f"{label}: mean of {window} episodes ({seeds_note(ns)}){none}",
                ns,
                lw=1.6,
            )
        else:
            _curve(ax, d, "mean_abs_A", c, f"{label} ({seeds_note(ns)})", ns, lw=1)
    ax.set_xlabel("episode")
    ax.xaxis.set_major_locator(MaxNLocator(integer=True))
    ax.set_ylabel(r"mean $|A^{w}|$")
    _log_if_positive(ax, ep.loc[ep.learner.isin(shown), "mean_abs_A"])
    ax.legend(loc="best", fontsize=7, framealpha=0.85)


def _pareto_panel(fig: Figure, ax3: Axes3D, ep: pd.DataFrame, learners: list[str]) -> None:
    """The observed objectives (f1, f2, f4, or f3 without f4) of the first seed of MOBO (else
    the last learner), with their Pareto front (a front is one seed's: the title says which)."""
    src = "mobo" if "mobo" in learners else learners[-1]
    d = ep[ep.learner == src]
    n_seeds, seed = d.seed.nunique(), d.seed.min()
    d = d[d.seed == seed]
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
        sc = ax3.scatter(
            *Y[ok & ~mask].T,
            c=d["episode"].to_numpy()[ok & ~mask],
            cmap="Greys",
            s=8,
            alpha=0.7,
            label="observations",
        )
        ax3.scatter(*Y[mask].T, marker="*", color="red", s=60, label="Pareto front")
        if (ok & ~mask).any():
            fig.colorbar(sc, ax=ax3, shrink=0.6, pad=0.1, label="episode")
        ax3.legend(fontsize=7)
    ax3.set_xlabel(labels[0])
    ax3.set_ylabel(labels[1])
    ax3.set_zlabel(labels[2])
    ax3.set_box_aspect(None, zoom=0.85)  # room for the z label
    of = f", seed {seed} of {n_seeds}" if n_seeds > 1 else ""
    ax3.set_title(f"Pareto front of the {LABELS.get(src, src)} observations{of}", fontsize=9)


def _traj_figure(tr: pd.DataFrame, info: dict, learner: str, kind: str) -> Figure:
    names = info["state_names"] if kind == "x" else info["input_names"]
    ref = info["x_ref"] if kind == "x" else info["u_ref"]
    lb = info["x_lb"] if kind == "x" else info["u_lb"]
    ub = info["x_ub"] if kind == "x" else info["u_ub"]
    fig = Figure(figsize=(7, 2.2 * len(names) + 0.8), layout="constrained")
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
    n_learn, n_final = learning.seed.nunique(), final.seed.nunique()
    of = f": median and IQR of {n_final} seeds, per start" if n_final > 1 else ""
    learning_label = "during learning" + (f" ({n_learn} seeds)" if n_learn > 1 else "")
    handles = [
        Line2D([], [], color="tab:green", label="imperfect MPC (theta0)"),
        Line2D([], [], color="grey", label=learning_label),
        Line2D([], [], color="tab:blue", label=f"learned MPC ({LABELS.get(learner, learner)}{of})"),
        Line2D([], [], color="tab:orange", ls="--", label="reference"),
        Line2D([], [], color="red", ls="--", label="limits"),
    ]
    fig.legend(handles=handles, fontsize=7, loc="outside lower center", ncol=3)
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


def make_figures(
    run_dir: str | Path, learner: str | None = None, summary: dict | None = None
) -> list[Path]:
    """Write figures 1-4 (PNG and PDF) into ``run_dir/figures``; return the paths.
    ``summary``: the run's summary (default: ``summary.json``)."""
    run_dir = Path(run_dir)
    for name in ("episodes.parquet", "trajectories.parquet"):
        if not (run_dir / name).exists():
            raise ValueError(f"{run_dir} has no {name}: nothing to plot (is the run started?)")
    ep = pd.read_parquet(run_dir / "episodes.parquet")
    tr = pd.read_parquet(run_dir / "trajectories.parquet")
    if summary is None:
        summary = json.loads((run_dir / "summary.json").read_text())
    info = summary["system_info"]
    present = list(dict.fromkeys(ep["learner"]))
    learners = [n for n in summary["learners"] if n in present] or present
    if not learners:
        raise ValueError(f"{run_dir} has no episodes to plot yet")
    if learner is None:
        learner = "mobo" if "mobo" in learners else learners[-1]
    elif learner not in learners and learner in summary["learners"]:
        raise ValueError(f"learner '{learner}' has no episodes yet; with episodes: {learners}")
    elif learner not in learners:
        raise ValueError(f"learner '{learner}' is not in this run; allowed: {learners}")
    out = run_dir / "figures"
    out.mkdir(exist_ok=True)
    note = partial_note(summary, ep)
    paths = _save(fig1(ep, summary, learners), out, FIGURES[0], note)
    paths += _save(fig2(ep, learners, reference_window(summary)), out, FIGURES[1], note)
    paths += _save(_traj_figure(tr, info, learner, "x"), out, FIGURES[2], note)
    paths += _save(_traj_figure(tr, info, learner, "u"), out, FIGURES[3], note)
    fig5 = identified_figure(ep, summary, learners)
    if fig5 is not None:
        paths += _save(fig5, out, IDENTIFIED, note)
    return paths


def partial_note(summary: dict, ep: pd.DataFrame) -> str:
    """What a figure of a run that has not ended says of it: the episodes each unfinished job
    has, of the run's budget ("" when every job of the run has ended)."""
    budget = int(summary.get("settings", {}).get("episodes", 0))
    seeds = summary.get("settings", {}).get("seeds", [])
    done = ep.groupby(["learner", "seed"])["episode"].nunique()
    short = []
    for name in summary.get("learners", {}):
        for seed in seeds:
            n = int(done.get((name, seed), 0))
            if n < budget:
                short.append(f"{name} seed {seed}: {n} of {budget} episodes")
    if not short:
        return ""
    return f"A partial run: {'; '.join(short)}"


def identified_figure(ep: pd.DataFrame, summary: dict, learners: list[str]) -> Figure | None:
    """The model parameters identified after each episode (median and interquartile band over
    seeds, per learner that identifies), with the MPC's nominal values, where known the
    plant's true values, and a bound of the identification that a final fit sits on; None when
    no learner identifies."""
    if "identified" not in ep.columns:
        return None
    who = {n: summary["learners"].get(n, {}).get("identified_names") or [] for n in learners}
    who = {n: names for n, names in who.items() if names}
    if not who:
        return None
    names = list(dict.fromkeys(p for v in who.values() for p in v))
    fig = Figure(figsize=(4.2 * min(3, len(names)), 2.8 * int(np.ceil(len(names) / 3))))
    axes = fig.subplots(int(np.ceil(len(names) / 3)), min(3, len(names)), squeeze=False)
    for k, name in enumerate(names):
        ax = axes.flat[k]
        held = _parameter_panel(ax, ep, name, who, summary)
        if held and k:
            ax.legend(fontsize=7)
        ax.set_title(name, fontsize=9)
        ax.set_xlabel("episode")
    for ax in list(axes.flat)[len(names) :]:
        ax.set_visible(False)
    axes.flat[0].legend(fontsize=7)
    fig.suptitle("Model parameters identified from the plant's transitions")
    fig.tight_layout()
    return fig


def _parameter_panel(
    ax: Axes, ep: pd.DataFrame, name: str, who: dict[str, list[str]], summary: dict
) -> bool:
    """The panel of the model parameter ``name``: its identified value per learner that
    identifies it (``who``: learner -> its identified parameters), the MPC's nominal value,
    where known the plant's, and a bound of the identification that a final fit sits on
    (returned: whether there is one)."""
    for learner, ids in who.items():
        if name not in ids:
            continue
        d = ep[ep["learner"] == learner].copy()
        j = ids.index(name)
        d["value"] = [v[j] if v is not None and len(v) > j else np.nan for v in d["identified"]]
        color, label = COLORS.get(learner, "k"), LABELS.get(learner, learner)
        _curve(ax, d, "value", color, label, d["seed"].nunique())
    info = summary.get("system_info", {})
    pnames = info.get("param_names", [])
    nominal, true = info.get("nominal_params"), info.get("true_params")
    if name in pnames:
        i = pnames.index(name)
        if nominal is not None:
            ax.axhline(nominal[i], color="grey", ls=":", lw=1, label="nominal model")
        if true is not None:
            ax.axhline(true[i], color="k", ls="--", lw=1, label="plant")
    held = {
        (b["bound"], b["value"])
        for n in who
        for b in summary["learners"][n].get("identified_at_bound") or []
        if b["name"] == name
    }
    for side, value in sorted(held):  # a bound the fit ends on
        ax.axhline(value, color="tab:red", ls="-.", lw=1, label=f"{side} bound (fit held)")
    return bool(held)
