"""Fault injection: failed MPC solves at random steps, NaN and inf objectives, a learner
whose proposal raises and a deployed theta whose evaluation runs the plant away; each is
recorded and the run goes on, with no crash."""

from __future__ import annotations

import math

import numpy as np
import pytest
from typer.testing import CliRunner

from mpcmobo.cli import app
from mpcmobo.experiment import loop, storage, study
from mpcmobo.experiment.evaluation import Evaluator
from mpcmobo.experiment.settings import load_settings
from mpcmobo.experiment.study import run_study
from mpcmobo.learners.gp import BOLearner
from mpcmobo.learners.identified import IdentifyFirst
from mpcmobo.learners.mpc_rl import MPCRL
from mpcmobo.mpc import ParametricMPC
from mpcmobo.plots import make_figures

EPISODES = 8
FAST_SEARCH = {"num_restarts": 2, "raw_samples": 32, "maxiter": 20}  # a cheap acquisition search


def small(learners, identify=False, bo=None, **kw):
    """A short study on ``lq``: the learners tune the nominal model unless ``identify``; ``bo``:
    more options of the bo learner. Every candidate runs (no exploration budget): the faults
    are injected into the plant's episodes, and the budget would add closed loops on the
    model."""
    kw.setdefault("exploration", {"budget": math.inf})
    return load_settings(
        None,
        system={"name": "lq", "identify": identify},
        learners=learners,
        episodes=EPISODES,
        steps=8,
        workers=1,
        evaluation={"n_starts": 2},
        learner_options={"bo": {"n_init": 3, "search": FAST_SEARCH, **(bo or {})}},
        **kw,
    )


def test_failed_solves_at_random_steps_use_the_fallback_and_are_recorded(tmp_path, monkeypatch):
    rng = np.random.default_rng(14)
    injected = []
    original = ParametricMPC.solve

    def flaky(self, x, theta=None, sensitivities=True, **kwargs):
        if sensitivities and rng.random() < 0.15:  # a learning episode's solve
            injected.append(1)
            return self.solver.failed("Injected_Failure", 0, sensitivities)
        return original(self, x, theta, sensitivities, **kwargs)

    monkeypatch.setattr(ParametricMPC, "solve", flaky)
    summary = run_study(small(["mpc-rl", "bo"]), tmp_path / "run")
    assert summary["complete"] is True
    df = storage.read_episodes(tmp_path / "run")
    assert len(df) == 2 * EPISODES and (df.error == "").all()
    assert df.solver_failures.sum() == len(injected) > 0
    hit = df[df.solver_failures > 0]
    assert len(hit) > 0 and np.isfinite(hit.f1).all()  # the episode went on with the fallback


@pytest.mark.parametrize("learner", ["mpc-rl", "bo"])
def test_nan_and_inf_objectives_are_recorded_not_fitted(tmp_path, monkeypatch, learner):
    bad = {2: (0, math.nan), 3: (0, math.inf), 5: (1, -math.inf), 6: (3, math.nan)}
    original = loop.episode_result
    calls = []

    def corrupt(record, critic, previous_Vc, beta=1.0, **kw):
        result, cr = original(record, critic, previous_Vc, beta, **kw)
        k = len(calls)
        calls.append(k)
        if k in bad:
            i, value = bad[k]
            result.objectives = result.objectives.copy()
            result.objectives[i] = value
        return result, cr

    monkeypatch.setattr(loop, "episode_result", corrupt)
    summary = run_study(small([learner]), tmp_path / "run")
    assert summary["complete"] is True
    df = storage.read_episodes(tmp_path / "run")
    assert len(df) == EPISODES and (df.error == "").all()
    for k, (i, value) in bad.items():
        got = df.loc[k, f"f{i + 1}"]
        assert (math.isnan(got) and math.isnan(value)) or got == value
    incumbents = np.array(df.incumbent.tolist())
    assert np.isfinite(incumbents).all()
    if learner == "bo":  # an episode with a non-finite objective is never the incumbent
        thetas = np.array(df.theta.tolist())
        first = [
            next(j for j in range(len(thetas)) if np.array_equal(thetas[j], t)) for t in thetas
        ]
        for j in range(EPISODES):
            for k in bad:
                if first[k] == k and k <= j:
                    assert not np.array_equal(incumbents[j], thetas[k])


@pytest.mark.parametrize(
    "learner, cls, identify",
    [("mpc-rl", MPCRL, False), ("bo", BOLearner, False), ("bo", IdentifyFirst, True)],
)
def test_a_failing_proposal_is_recorded_and_the_incumbent_runs(
    tmp_path, monkeypatch, learner, cls, identify
):
    original = cls.propose
    calls = []

    def failing(self):
        calls.append(1)
        if len(calls) in (3, 6):
            raise RuntimeError("injected failure in the proposal")
        return original(self)

    monkeypatch.setattr(cls, "propose", failing)
    summary = run_study(small([learner], identify), tmp_path / "run")
    assert summary["complete"] is True
    df = storage.read_episodes(tmp_path / "run")
    assert len(df) == EPISODES
    for k in (2, 5):
        assert "proposal failed" in df.error[k] and "injected failure" in df.error[k]
        assert np.array_equal(df.theta[k], df.incumbent[k - 1])  # the incumbent ran
        assert np.isfinite(df.f1[k])
    assert (df.error.drop([2, 5]) == "").all()


@pytest.mark.parametrize(
    ("error", "recorded"),
    [
        (
            FloatingPointError("the plant ran away at step 3: state [1e+70]"),
            "evaluation: the plant ran away at step 3",
        ),
        (RuntimeError("plant step failure"), "evaluation: RuntimeError: plant step failure"),
    ],
)
def test_an_evaluation_that_runs_the_plant_away_is_recorded_and_the_run_goes_on(
    tmp_path, monkeypatch, error, recorded
):
    """A plant that runs away, or raises, from an evaluation start: J_eval is inf with the
    error, the run goes on. (bo deploys its GP's best point, so the final incumbent is not
    theta0, whose J_eval and episodes are the reference's.)"""
    armed = []
    compute = study.compute_reference

    def reference_then_arm(settings):
        ref = compute(settings)
        armed.append(1)  # the jobs' evaluations run the plant away, not the reference's
        return ref

    original = Evaluator.episodes

    def runaway(self, theta, model="imperfect"):
        if armed:
            raise error
        return original(self, theta, model)

    monkeypatch.setattr(study, "compute_reference", reference_then_arm)
    monkeypatch.setattr(Evaluator, "episodes", runaway)
    summary = run_study(small(["bo"], bo={"deploy": {"rule": "incumbent"}}), tmp_path / "run")
    assert summary["complete"] is True
    df = storage.read_episodes(tmp_path / "run")
    assert len(df) == EPISODES
    last = df.iloc[-1]
    assert math.isinf(last.J_eval_incumbent) and last.J_eval_incumbent > 0
    assert last.error.startswith(recorded)
    assert math.isfinite(df.J_eval_incumbent.iloc[0])  # theta0's, from the reference
    seed = storage.read_json(tmp_path / "run" / "summary.json")["learners"]["bo"]["per_seed"]["0"]
    assert seed["J_final"] is None and seed["regressions"] >= 1  # inf: not a number in JSON
    assert make_figures(tmp_path / "run")  # the figures skip what they cannot draw
    if isinstance(error, RuntimeError):
        return

    def runaway_J(self, theta, model="imperfect"):
        if theta is not None:  # the saved incumbents, not J* or theta0's J_eval
            raise FloatingPointError("the plant ran away at step 3: state [1e+70]")
        return 1.0

    monkeypatch.setattr(Evaluator, "J_eval", runaway_J)
    result = CliRunner().invoke(app, ["evaluate", str(tmp_path / "run")], env={"COLUMNS": "200"})
    assert result.exit_code == 0, result.output
    assert "the plant ran away" in result.output


def test_a_plant_that_fails_while_the_reference_is_computed_ends_the_run_with_a_message(
    tmp_path, monkeypatch
):
    """J* and J(theta0) are what every J_eval is measured against: a plant that raises while
    they are computed ends the run with a message that says so, not a traceback."""

    def failing(self, theta, model="imperfect"):
        raise RuntimeError("plant step failure")

    monkeypatch.setattr(Evaluator, "episodes", failing)
    settings = small(["bo"])
    from mpcmobo.experiment.settings import settings_to_toml

    (tmp_path / "s.toml").write_text(settings_to_toml(settings))
    res = CliRunner().invoke(
        app, ["run", "-c", str(tmp_path / "s.toml"), "--out", str(tmp_path / "run"), "-q"]
    )
    text = " ".join(res.output.split())
    assert res.exit_code == 1 and "Traceback" not in text, text
    assert (
        "computing J(theta0), theta0's MPC on the plant from the evaluation starts failed: "
        "RuntimeError: plant step failure" in text
    )
    assert not (tmp_path / "run").exists()  # nothing recorded: the same --out starts anew
    (tmp_path / "empty").mkdir()  # an empty directory given is left empty
    args = ["run", "-c", str(tmp_path / "s.toml"), "--out", str(tmp_path / "empty"), "-q"]
    assert CliRunner().invoke(app, args).exit_code == 1
    assert (tmp_path / "empty").is_dir() and not any((tmp_path / "empty").iterdir())


def test_a_state_that_is_not_finite_fails_the_episode_by_name_and_the_summary_says_so(
    tmp_path, monkeypatch
):
    """A plant that returns a NaN state for one step of one learning episode (a sensor
    dropout): that episode fails, named as a state that is not finite (not as a divergence),
    the run goes on, and the summary and the run's warnings name the failed episode."""
    from mpcmobo.cli import failed_warnings
    from mpcmobo.systems.plant import SystemPlant

    compute, armed, calls = study.compute_reference, [], []

    def reference_then_arm(settings):
        ref = compute(settings)
        armed.append(1)
        return ref

    step = SystemPlant.step

    def dropout(self, action):
        obs, reward, terminated, truncated, info = step(self, action)
        if armed:
            calls.append(1)
            if len(calls) == 20:  # once, in a learning episode
                obs = np.full_like(obs, np.nan)
        return obs, reward, terminated, truncated, info

    monkeypatch.setattr(study, "compute_reference", reference_then_arm)
    monkeypatch.setattr(SystemPlant, "step", dropout)
    summary = run_study(small(["mpc-rl"]), tmp_path / "run")
    assert summary["complete"] is True
    df = storage.read_episodes(tmp_path / "run")
    failed = df[df.mean_stage_cost.isna()]
    assert len(failed) == 1 and len(df) == EPISODES
    e = int(failed.episode.iloc[0])
    assert "the plant returned a state that is not finite at step" in failed.error.iloc[0]
    per = summary["learners"]["mpc-rl"]["per_seed"]["0"]
    assert [f["episode"] for f in per["failed_episodes"]] == [e]
    assert summary["learners"]["mpc-rl"]["failed_episodes"] == 1
    (line,) = failed_warnings(summary)
    assert line.startswith(f"mpc-rl seed 0: 1 episode(s) failed (episode {e}: PlantDiverged: the")
    assert "never deployed" in line


def test_episodes_with_failed_solves_are_named_in_the_summary_and_warned():
    """A recorded episode in which MPC solves failed (a theta whose model is not finite fails
    every solve; the fallback input drives the plant) is listed per seed with its count, and
    the run's warnings name it; a failed episode is counted among the failed ones alone."""
    import pandas as pd

    from mpcmobo.cli import unsolved_warnings
    from mpcmobo.experiment.summary import _unsolved_episodes

    rows = pd.DataFrame(
        {"episode": [0, 1, 2, 3], "solver_failures": [0, 36, 2, 36]}
        | {"mean_stage_cost": [1.0, 184.4, 3.0, np.nan]}
    )
    hit = _unsolved_episodes(rows)
    assert hit == [{"episode": 1, "failed_solves": 36}, {"episode": 2, "failed_solves": 2}]
    summary = {"learners": {"mobo": {"per_seed": {"0": {"unsolved_episodes": hit}}}}}
    (line,) = unsolved_warnings(summary)
    assert line.startswith("mobo seed 0: MPC solves failed in 2 episode(s) (episode 1: 36 failed")
    assert "fallback input" in line and "not finite" in line
    assert unsolved_warnings({"learners": {"mobo": {"per_seed": {"0": {}}}}}) == []
