"""Figures 1-4 from the records of a small real run (lq, two learners, two seeds), checked for
their content: the drawn lines are the medians of the records, the bands their quartiles, the
legends say how many seeds, and each curve of Fig. 1 is drawn against a reference computed with
the same formula on the same kind of episodes."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pandas as pd
import pytest
from matplotlib.collections import PolyCollection
from matplotlib.colors import to_rgb
from matplotlib.image import imread
from typer.testing import CliRunner

from mpcmobo.cli import app
from mpcmobo.experiment.build import build_system
from mpcmobo.experiment.evaluation import Evaluator, make_evaluator
from mpcmobo.experiment.job import _learning_run
from mpcmobo.experiment.rundir import RunDirectory
from mpcmobo.experiment.settings import load_settings
from mpcmobo.experiment.study import run_study
from mpcmobo.experiment.training_reference import training_references
from mpcmobo.mpc import ParametricMPC, rollout
from mpcmobo.plots import FIGURES, _traj_figure, fig1, fig2, pareto_mask
from mpcmobo.rl.objectives import f1_closed_loop_cost, mean_stage_cost

LEARNERS = ["mpc-rl", "bo"]
K = 3  # n_cycle_starts: the episodes of J~* per seed and the window of the moving means


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("plots") / "run"
    s = load_settings(
        None,
        system={"name": "lq"},
        learners=LEARNERS,
        episodes=6,
        steps=10,
        seeds=[0, 1],
        start_mode="cycle",
        n_cycle_starts=K,
        evaluation={"n_starts": 2, "eval_every": 2},
        records={"trajectory_every": 2},
        workers=1,
    )
    run_study(s, out)
    return out


def _records(run):
    ep = pd.read_parquet(run / "episodes.parquet")
    summary = json.loads((run / "summary.json").read_text())
    return ep, summary


def _lines(ax) -> dict:
    return {line.get_label(): line for line in ax.get_lines()}


def _line(ax, *words):
    """The one line of ``ax`` whose label holds every word."""
    found = [ln for lab, ln in _lines(ax).items() if all(w in lab for w in words)]
    assert len(found) == 1, (words, list(_lines(ax)))
    return found[0]


def _legend(ax) -> list[str]:
    return [t.get_text() for t in ax.get_legend().get_texts()]


def test_plot_writes_all_four_figures(small_run):
    res = CliRunner().invoke(app, ["plot", str(small_run)])
    assert res.exit_code == 0, res.output
    for name in FIGURES:
        for ext in ("png", "pdf"):
            p = small_run / "figures" / f"{name}.{ext}"
            assert p.exists() and p.stat().st_size > 1000, p
    assert (small_run / "figures" / "fig1_performance.png").read_bytes()[:4] == b"\x89PNG"
    assert (small_run / "figures" / "fig3_states.pdf").read_bytes()[:4] == b"%PDF"
    # each PNG is a drawn figure, not a blank canvas: many colours, and the learner's colour
    # (MPC-RL: tab:green) in the curves of figures 1-4 (fig. 3 and 4: the imperfect MPC)
    green = np.array(to_rgb("tab:green"))
    for name in FIGURES:
        img = imread(small_run / "figures" / f"{name}.png")[..., :3]
        assert img.shape[0] > 300 and img.shape[1] > 500, name
        assert len(np.unique(img.reshape(-1, 3).round(2), axis=0)) > 20, name
        assert np.any(np.all(np.abs(img - green) < 0.02, axis=-1)), name


def test_references_use_the_formula_of_their_curves(small_run):
    """J~* is f1 (the function that gives every learner's J~) of the perfect-model MPC's
    episodes from the learners' training starts with the learners' exploration noise; J* is the
    mean stage cost (the function of J_eval) of the perfect-model MPC on the evaluation starts.
    The episodes are drawn again here, independently of the study, and checked against the
    records: the learners' own first episodes are reproduced exactly."""
    ep, summary = _records(small_run)
    settings = RunDirectory(small_run).saved_settings()
    system = build_system(settings)
    perfect = ParametricMPC(system, model="perfect", **settings.mpc.options())
    assert summary["J_tilde_star_episodes"] == K
    refs = []
    for seed in settings.seeds:
        # the curve: a learner's episodes, drawn again, give its recorded J~ = f1(episode)
        learner_run = _learning_run(settings, build_system(settings, "mpc-rl"), "mpc-rl", seed)
        rows = ep[(ep.learner == "mpc-rl") & (ep.seed == seed)].sort_values("episode")
        for recorded in rows.head(K).itertuples():
            row, record = learner_run.run_episode()
            np.testing.assert_array_equal(row["x0"], recorded.x0)
            assert row["J_tilde"] == recorded.J_tilde == f1_closed_loop_cost(record)
        # the reference: f1 of the perfect-model MPC on the same starts with the same noise
        run = _learning_run(settings, system, "mpc-rl", seed)
        values = []
        for episode in range(K):
            x0 = run.next_start()
            for name in LEARNERS:  # every learner's episode l started there
                got = ep[(ep.learner == name) & (ep.seed == seed) & (ep.episode == episode)]
                np.testing.assert_array_equal(got.x0.iloc[0], x0)
            run.exploration.episode = episode
            record = rollout(
                system, perfect, None, x0, run.steps, rng=run.rng_noise, exploration=run.exploration
            )
            values.append(f1_closed_loop_cost(record))
            run.episode += 1
        assert summary["J_tilde_star_per_seed"][str(seed)] == pytest.approx(np.mean(values))
        refs.append(np.mean(values))
    assert summary["J_tilde_star"] == pytest.approx(np.median(refs))
    # J* and J_eval: the mean stage cost on the evaluation starts, without exploration
    evaluator = make_evaluator(settings, system)
    steps = settings.evaluation.steps

    def J(mpc, theta):
        return np.mean(
            [mean_stage_cost(rollout(system, mpc, theta, x0, steps)) for x0 in evaluator.starts]
        )

    assert summary["J_star"] == pytest.approx(J(perfect, None))
    row = ep[np.isfinite(ep.J_eval_incumbent)].iloc[-1]
    own = build_system(settings, row.learner)  # with the identified parameters in theta
    imperfect = ParametricMPC(own, model="imperfect", **settings.mpc.options())
    assert row.J_eval_incumbent == pytest.approx(J(imperfect, np.asarray(row.incumbent)))


def test_training_reference_with_random_starts(small_run):
    """With random starts, J~* of a seed is f1 on as many episodes as J* has starts
    (evaluation.n_starts), from the seed's random training starts."""
    settings = RunDirectory(small_run).saved_settings(start_mode="random")
    system = build_system(settings)
    refs = training_references(settings, system)
    assert [r.seed for r in refs] == settings.seeds
    for r in refs:
        run = _learning_run(settings, system, "bo", r.seed)
        assert len(r.J_tilde) == settings.evaluation.n_starts
        for x0 in r.x0:
            np.testing.assert_array_equal(x0, run.next_start())
    assert refs[0].x0 != refs[1].x0


def _three_seeds(ep: pd.DataFrame) -> pd.DataFrame:
    """The records with a third seed whose costs are 10x seed 0's: its median differs from
    its mean, and from the mean of the other two."""
    extra = ep[ep.seed == 0].copy()
    extra["seed"] = 2
    for col in ("J_tilde", "J_eval_incumbent", "mean_abs_A"):
        extra[col] *= 10
    return pd.concat([ep, extra], ignore_index=True)


@pytest.mark.parametrize("seeds", [2, 3])
def test_fig1_draws_medians_against_references(small_run, seeds):
    """Per learner: the per-episode median of J~, the median over seeds of its mean over K
    episodes with the quartiles as a band, J~* of the summary; J_eval of the deployed theta
    (the last evaluated incumbent, per seed) with its band, J* of the summary; legends with
    the seed count."""
    ep, summary = _records(small_run)
    if seeds == 3:
        ep = _three_seeds(ep)
    fig = fig1(ep, summary, LEARNERS)
    axes = np.array(fig.axes).reshape(len(LEARNERS), 2)
    for (ax, ax_eval), name in zip(axes, LEARNERS):
        d = ep[ep.learner == name].sort_values(["seed", "episode"])
        raw = _line(ax, "per episode")
        np.testing.assert_allclose(raw.get_ydata(), d.groupby("episode").J_tilde.median())
        mean = d.groupby("seed").J_tilde.transform(lambda v: v.rolling(K).mean())
        med = mean.groupby(d.episode).median().dropna()
        curve = _line(ax, f"mean of {K} episodes")
        np.testing.assert_array_equal(curve.get_xdata(), med.index)
        np.testing.assert_allclose(curve.get_ydata(), med.to_numpy())
        assert curve.get_xdata()[0] == K - 1  # a mean covers a whole cycle of the starts
        (band,) = [c for c in ax.collections if isinstance(c, PolyCollection)]
        edge = band.get_paths()[0].vertices[:, 1]
        q = mean.groupby(d.episode).quantile([0.25, 0.75]).unstack().dropna()
        for v in np.r_[q[0.25], q[0.75]]:  # the band runs from the lower to the upper quartile
            assert np.isclose(edge, v).any(), (v, edge)
        ref = _line(ax, r"\tilde J^\star")
        np.testing.assert_allclose(ref.get_ydata(), summary["J_tilde_star"])
        assert any(f"{seeds} seeds" in t for t in _legend(ax)), _legend(ax)
        deployed = d.groupby("seed").J_eval_incumbent.ffill()
        med = deployed.groupby(d.episode).median()
        curve = _line(ax_eval, "deployed")
        np.testing.assert_array_equal(curve.get_xdata(), med.index)
        np.testing.assert_allclose(curve.get_ydata(), med.to_numpy())
        np.testing.assert_allclose(_line(ax_eval, r"J^\star").get_ydata(), summary["J_star"])
        assert any(f"{seeds} seeds" in t for t in _legend(ax_eval)), _legend(ax_eval)
        assert [c for c in ax_eval.collections if isinstance(c, PolyCollection)]


def test_fig1_one_seed_and_old_runs(small_run, tmp_path):
    """One seed: single lines, no bands, "1 seed" in the legend. A run whose summary has no
    J~* says so in the panel and draws no unlike reference; `mpcmobo plot` draws it."""
    ep, summary = _records(small_run)
    one = ep[(ep.seed == 0) & (ep.learner == "bo")]
    ax, ax_eval = fig1(one, summary, ["bo"]).axes[:2]
    for a in (ax, ax_eval):
        assert not [c for c in a.collections if isinstance(c, PolyCollection)]
        assert any("1 seed" in t for t in _legend(a)), _legend(a)
    np.testing.assert_allclose(
        _line(ax_eval, "deployed").get_ydata(), one.J_eval_incumbent.ffill().to_numpy()
    )
    old = {k: v for k, v in summary.items() if not k.startswith("J_tilde_star")}
    ax = fig1(ep, old, ["bo"]).axes[0]
    assert not [lab for lab in _lines(ax) if "tilde J^\\star" in lab]
    assert "no like-for-like reference in this run" in [t.get_text() for t in ax.texts]
    run = tmp_path / "old"
    shutil.copytree(small_run, run, ignore=shutil.ignore_patterns("figures"))
    (run / "summary.json").write_text(json.dumps(old))
    res = CliRunner().invoke(app, ["plot", str(run)])
    assert res.exit_code == 0, res.output


def test_fig2_and_fig3_draw_the_records(small_run):
    """Fig. 2: the mean over K episodes of mean |A^w|, median over seeds, with the seed count;
    the Pareto panel names its seed. Fig. 3: the final incumbent's evaluation per start, median
    over seeds."""
    ep, summary = _records(small_run)
    fig = fig2(_three_seeds(ep), LEARNERS, window=K)
    ax = fig.axes[0]
    d = _three_seeds(ep)
    d = d[d.learner == "mpc-rl"].sort_values(["seed", "episode"])
    mean = d.groupby("seed").mean_abs_A.transform(lambda v: v.rolling(K).mean())
    curve = _line(ax, "MPC-RL", f"mean of {K}")
    np.testing.assert_allclose(curve.get_ydata(), mean.groupby(d.episode).median().dropna())
    assert "3 seeds" in curve.get_label()
    assert "seed 0 of 3" in fig.axes[1].get_title()
    tr = pd.read_parquet(small_run / "trajectories.parquet")
    fig = _traj_figure(tr, summary["system_info"], "bo", "x")
    final = tr[(tr.phase == "final") & (tr.learner == "bo")]
    blue = [ln for ln in fig.axes[0].get_lines() if ln.get_color() == "tab:blue"]
    assert len(blue) == final.start.nunique() == 2
    for line, (_, g) in zip(blue, final.groupby("start")):
        np.testing.assert_allclose(line.get_ydata(), g.groupby("t").x_p.median())
    assert any("2 seeds" in t.get_text() for t in fig.legends[0].get_texts())


def test_fig2_leaves_out_episodes_without_a_critic(small_run):
    """An episode whose critic was not fitted (a converged tuning's, without exploration) has
    no advantage: recorded as 0, it is not drawn as one (the curve has a gap there)."""
    ep, _ = _records(small_run)
    ep = ep.copy()
    quiet = (ep.learner == "mpc-rl") & (ep.episode == 3)
    ep.loc[quiet, ["critic_ok", "mean_abs_A"]] = [False, 0.0]
    curve = _line(fig2(ep, LEARNERS, window=1).axes[0], "MPC-RL", "MPC-RL")
    drawn = dict(zip(curve.get_xdata(), curve.get_ydata(), strict=True))
    assert 3 not in drawn and drawn  # the median over seeds skips it, not 0


def test_plot_errors(small_run, tmp_path):
    res = CliRunner().invoke(app, ["plot", str(tmp_path)])
    assert res.exit_code == 2 and "config.toml" in res.output
    res = CliRunner().invoke(app, ["plot", str(small_run), "--learner", "mobo"])
    assert res.exit_code == 2 and "not in this run" in res.output
    bare = tmp_path / "bare"  # a run's directory without its trajectories
    bare.mkdir()
    for name in ("config.toml", "summary.json", "episodes.parquet"):
        (bare / name).write_bytes((small_run / name).read_bytes())
    res = CliRunner().invoke(app, ["plot", str(bare)])
    assert res.exit_code == 2 and "has no trajectories.parquet" in " ".join(res.output.split())


def test_pareto_mask():
    Y = np.array([[1.0, 2.0], [2.0, 1.0], [2.0, 2.0], [0.5, 3.0], [np.nan, 0.0], [1.0, 2.0]])
    assert pareto_mask(Y).tolist() == [True, True, False, True, False, True]


def test_reproduction_tables_match_the_summary(small_run, benchmark_script):
    """benchmarks/reproduction.py (the tables of docs/reproduction.md): per learner, the final
    J_eval/J* of its claim-1 row is the median over seeds of summary.json's J_final / J*, the
    episode counts are summary.json's, and every claim prints a row per learner."""
    rep = benchmark_script("reproduction")
    ep, tr, summary = rep.load(small_run)
    rows = {r.split(" | ")[0].lstrip("| "): r.split(" | ") for r in rep.claim1("x", ep, summary)}
    for name in LEARNERS:
        per_seed = summary["learners"][name]["per_seed"].values()
        final = np.median([v["J_final"] / summary["J_star"] for v in per_seed])
        assert rows[name][3].split(" ")[0] == f"{final:.2f}"
        to2 = [v["episodes_to_2pct"] for v in per_seed]
        cells = [c.split("/")[2] for c in rows[name][5].split(", ")]
        assert cells == [str(v) if v is not None else "-" for v in to2]
    for fn, data in ((rep.claim3, tr), (rep.claim4, ep)):
        body = "\n".join(fn("x", data, summary))
        assert all(name in body for name in LEARNERS)


def test_recheck_on_the_evaluation_starts_reproduces_J_eval(small_run, benchmark_script):
    """benchmarks/recheck.py re-evaluates the final and worst deployed thetas on fresh starts;
    given the evaluation's own number of starts and seed, its J/J* of each theta is the run's
    J_eval/J* of it, and theta0 there is J_eval(theta0)/J*."""
    rc = benchmark_script("recheck")
    summary = json.loads((small_run / "summary.json").read_text())
    rows = rc.recheck(small_run, starts=2, seed=2025, only_seeds=[0])
    assert {(r["learner"], r["theta"]) for r in rows} == {
        (n, w) for n in LEARNERS for w in ("final", "worst")
    }
    for r in rows:
        assert r["seed"] == 0 and r["starts"] == 2
        assert r["J_fresh_ratio"] == pytest.approx(r["J_eval_ratio"], rel=1e-9)
        assert r["J0_fresh_ratio"] == pytest.approx(
            summary["J_initial"] / summary["J_star"], rel=1e-9
        )
        assert r["regression"] == (r["J_fresh_ratio"] > r["J0_fresh_ratio"])
    other = rc.recheck(small_run, starts=2, seed=7, only_seeds=[0])
    assert any(abs(o["J0_fresh_ratio"] - r["J0_fresh_ratio"]) > 1e-6 for o, r in zip(other, rows))


def test_recheck_summary_names_the_seeds_that_end_above_identify(benchmark_script):
    """The summary's last column: per learner, the seeds whose final theta is above
    ``identify``'s of the same seed by more than 0.05%, on either set of starts, with the
    excess; "none" when no seed is; empty without ``identify``'s rows. A learner in two runs
    (with and without identification) is two rows, each named with its run."""
    rc = benchmark_script("recheck")

    def row(learner, seed, ev, fresh):
        return {
            "learner": learner,
            "seed": seed,
            "theta": "final",
            "J_eval_ratio": ev,
            "J_fresh_ratio": fresh,
            "J0_fresh_ratio": 4.0,
            "regression": False,
        }

    rows = [
        row("identify", 0, 1.0, 1.0),
        row("identify", 1, 1.0, 1.0),
        row("mobo", 0, 0.9, 1.0003),
        row("mobo", 1, 1.02, 0.99),
        row("bo", 0, 0.9, 0.95),
        row("bo", 1, 1.0, 1.005),
    ]
    assert rc.above_identify(rows) == {"mobo": "1 (eval +2.0%)", "bo": "1 (fresh +0.5%)"}
    assert rc.above_identify([r for r in rows if r["seed"] == 0]) == {"mobo": "none", "bo": "none"}
    assert rc.above_identify([r for r in rows if r["learner"] != "identify"]) == {
        "mobo": "",
        "bo": "",
    }
    table = rc.summary_table(rows, 100).splitlines()
    assert table[0].endswith("| seeds above `identify` |")
    assert table[3].endswith("| none | 1 (eval +2.0%) |")
    two = [dict(r, run="id") for r in rows] + [dict(row("mobo", 0, 2.0, 2.0), run="noid")]
    assert rc.above_identify(two) == {
        "mobo (id)": "1 (eval +2.0%)",
        "bo": "1 (fresh +0.5%)",
        "mobo (noid)": "0 (eval +100.0%), 0 (fresh +100.0%)",
    }


def test_recheck_counts_a_theta_that_runs_the_plant_away_as_a_regression(
    small_run, benchmark_script, monkeypatch
):
    rc = benchmark_script("recheck")
    original = Evaluator.episodes

    def runaway(self, theta, model="imperfect"):
        if theta is not None:  # the deployed thetas, not J*'s or theta0's MPC
            raise FloatingPointError("the plant ran away at step 3: state [1e+70]")
        return original(self, theta, model)

    monkeypatch.setattr(Evaluator, "episodes", runaway)
    rows = rc.recheck(small_run, starts=2, seed=7, only_seeds=[0], which=("final",))
    assert len(rows) == len(LEARNERS)
    for r in rows:
        assert r["J_fresh_ratio"] == math.inf and r["regression"] and r["wins"] == 0
        assert math.isfinite(r["J0_fresh_ratio"])


def test_a_one_episode_curve_is_drawn_as_a_point(small_run):
    """A run of one episode has one point per curve: drawn with a marker, not as an empty
    line."""
    ep, summary = _records(small_run)
    one = ep[ep.episode == 0]
    curve = _line(fig2(one, LEARNERS, window=1).axes[0], "MPC-RL", "MPC-RL")
    assert len(curve.get_xdata()) == 1 and curve.get_marker() == "o"


def test_the_figures_of_a_partial_run_say_so(small_run, tmp_path):
    """The figures of a run whose jobs have not all ended (an interrupted run, or one plotted
    while it runs) say at their foot which jobs have how many of the run's episodes; a finished
    run's figures carry no such note."""
    from mpcmobo.plots import partial_note

    ep, summary = _records(small_run)
    assert partial_note(summary, ep) == ""
    part = tmp_path / "run"
    shutil.copytree(small_run, part)
    cut = ep[~((ep.learner == "bo") & (ep.seed == 1) & (ep.episode >= 4))]
    cut.to_parquet(part / "episodes.parquet")
    note = partial_note(summary, cut)
    assert note == "A partial run: bo seed 1: 4 of 6 episodes"
    res = CliRunner().invoke(app, ["plot", str(part)])
    assert res.exit_code == 0, res.output
    from mpcmobo import plots

    drawn = []
    real_save = plots._save

    def spy(fig, out, name, note=""):
        paths = real_save(fig, out, name, note)
        drawn.append([t.get_text() for t in fig.texts])
        return paths

    plots._save = spy
    try:
        plots.make_figures(part)
    finally:
        plots._save = real_save
    assert len(drawn) >= 4 and all(note in texts for texts in drawn)


def test_a_failed_training_reference_episode_is_named_in_the_summary():
    """A perfect-model episode of J~* that failed (a NaN) leaves that seed's J~* null; the
    summary says why (``J_tilde_star_reason``) instead of a silent null."""
    from mpcmobo.experiment.records import Reference, TrainingReference
    from mpcmobo.experiment.training_reference import training_summary

    def reference(*training):
        return Reference(
            J_star=1.0, J_initial=2.0, theta0=np.zeros(1), system={}, training=list(training)
        )

    ok, bad = (
        TrainingReference(0, [1.0, 2.0], [[0.0]]),
        TrainingReference(1, [1.0, math.nan], [[0.0]]),
    )
    assert "J_tilde_star_reason" not in training_summary(reference(ok))
    one = training_summary(reference(ok, bad))
    assert (
        one["J_tilde_star"] == 1.5 and "seed(s) 1: their J~* is null" in one["J_tilde_star_reason"]
    )
    none = training_summary(reference(bad))
    assert none["J_tilde_star"] is None and none["J_tilde_star_reason"].endswith("so is the median")


def test_fig1_names_the_training_reference_of_random_starts(small_run):
    """Under random starts J~* is the perfect-model MPC on the first K training starts alone:
    the legend says so instead of "same starts", which holds under cycled starts only."""
    ep, summary = _records(small_run)
    summary = {**summary, "settings": {**summary["settings"], "start_mode": "random"}}
    ax = fig1(ep, summary, ["bo"]).axes[0]
    (label,) = [lab for lab in _lines(ax) if r"\tilde J^\star" in lab]
    assert f"the first {K} starts only" in label and "same starts" not in label, label
