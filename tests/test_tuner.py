"""Ask and tell (mpcmobo.Tuner, mpcmobo ask / tell / status): the user's own episode loop gives
the records of mpcmobo run; a crash between ask and tell loses nothing; bad trials and logs are
refused without changing what is recorded."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

import mpcmobo
from mpcmobo.cli import app
from mpcmobo.experiment.settings import load_settings
from mpcmobo.experiment.study import run_study
from mpcmobo.experiment.tuner import Tuner, TunerError, write_log
from mpcmobo.learners.switch import REFIT_GROWTH
from mpcmobo.systems.plant import SystemPlant

SRC = str(Path(__file__).resolve().parents[1] / "src")
FAST = {"n_init": 2, "search": {"num_restarts": 1, "raw_samples": 16, "maxiter": 10}}
SETTINGS = {
    "episodes": 4,
    "steps": 12,
    "start_mode": "cycle",
    "n_cycle_starts": 2,
    "evaluation": {"n_starts": 2, "eval_every": 2},
    "learner_options": {"bo": FAST},
}


def _episode(tuner: Tuner, trial, x0=None) -> tuple[np.ndarray, np.ndarray]:
    """The user's loop on the simulated plant: start at trial.x0 (or ``x0``), apply the
    trial's policy plus its noise, clipped, log states and inputs."""
    plant = SystemPlant(tuner.system)
    trial.restart()
    x, _ = plant.reset(seed=0, options={"x0": trial.x0 if x0 is None else x0})
    states, inputs = [x], []
    for k in range(trial.steps):
        u = np.clip(trial.policy(x) + trial.noise[k], tuner.system.u_lb, tuner.system.u_ub)
        x, *_ = plant.step(u)
        states.append(x)
        inputs.append(u)
    return np.array(states), np.array(inputs)


def _same_records(a: Path, b: Path) -> None:
    """episodes.parquet of two directories, equal in every column but the wall times and the
    excess cost: a study measures it on its simulated plant, a tuner, whose episodes ran on a
    plant it cannot simulate, predicts it on the deployed theta's own model (it agrees in
    where it is zero: the episodes that ran the deployed theta)."""
    ea, eb = pd.read_parquet(a / "episodes.parquet"), pd.read_parquet(b / "episodes.parquet")
    assert list(ea.columns) == list(eb.columns) and len(ea) == len(eb)
    np.testing.assert_array_equal(ea["excess_cost"] == 0, eb["excess_cost"] == 0)
    for col in ea.columns:
        if col.endswith("time_s") or col == "excess_cost":
            continue
        for x, y in zip(ea[col], eb[col], strict=True):
            if isinstance(x, str):
                assert x == y, col
            else:
                assert np.array_equal(np.asarray(x, float), np.asarray(y, float), equal_nan=True), (
                    col
                )


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    """mpcmobo run's records of bo on the CSTR with the tuner's settings."""
    out = tmp_path_factory.mktemp("study") / "run"
    settings = load_settings(None, learners=["bo"], seeds=[0], workers=1, **SETTINGS)
    run_study(settings, out)
    return out


def test_ask_and_tell_on_the_simulated_cstr_records_what_mpcmobo_run_records(study, tmp_path):
    tuner = mpcmobo.Tuner("cstr", "bo", tmp_path / "tuner", **SETTINGS)
    for _ in range(SETTINGS["episodes"]):
        trial = tuner.ask()
        tuner.tell(trial, *_episode(tuner, trial))
    _same_records(study, tmp_path / "tuner")
    assert np.array_equal(
        tuner.deployed, pd.read_parquet(study / "episodes.parquet").incumbent.iloc[-1]
    )
    assert tuner.status()["told"] == SETTINGS["episodes"]
    with pytest.raises(TunerError, match="budget"):
        tuner.ask()


def test_a_crash_between_ask_and_tell_loses_nothing(study, tmp_path):
    """The process is killed after its second ask; Tuner.load asks the same trial again and the
    records end as mpcmobo run's."""
    out = tmp_path / "tuner"
    script = textwrap.dedent(f"""
        import os, numpy as np, mpcmobo, json
        from mpcmobo.systems.plant import SystemPlant
        tuner = mpcmobo.Tuner("cstr", "bo", {str(out)!r}, **json.loads({json.dumps(json.dumps(SETTINGS))}))
        trial = tuner.ask()
        plant = SystemPlant(tuner.system)
        x, _ = plant.reset(seed=0, options={{"x0": trial.x0}})
        X, U = [x], []
        for k in range(trial.steps):
            u = np.clip(trial.policy(x) + trial.noise[k], tuner.system.u_lb, tuner.system.u_ub)
            x, *_ = plant.step(u); X.append(x); U.append(u)
        tuner.tell(trial, np.array(X), np.array(U))
        print(json.dumps(tuner.ask().theta.tolist()), flush=True)
        os.kill(os.getpid(), 9)
    """)
    env = {**os.environ, "PYTHONPATH": SRC}
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, env=env)
    assert proc.returncode == -9, proc.stderr
    asked = np.array(json.loads(proc.stdout.splitlines()[-1]))
    tuner = Tuner.load(out)
    trial = tuner.ask()
    assert trial.id == 1 and np.array_equal(trial.theta, asked)
    tuner.tell(trial, *_episode(tuner, trial))
    while tuner.episodes < SETTINGS["episodes"]:
        trial = tuner.ask()
        tuner.tell(trial, *_episode(tuner, trial))
    _same_records(study, out)


@pytest.fixture
def lq_tuner(tmp_path):
    tuner = Tuner("lq", "mpc-rl", tmp_path / "t", episodes=3, steps=6)
    return tuner, tuner.ask()


def test_bad_trials_and_logs_are_refused_and_nothing_recorded_changes(lq_tuner):
    tuner, trial = lq_tuner
    X, U = _episode(tuner, trial)
    ckpt = next((tuner.run_dir.path / "jobs").glob("*/checkpoint.pkl"))
    before = ckpt.read_bytes()
    cases = [
        ((trial.id + 1, X, U), "unknown trial 1: the pending trial is 0"),
        ((trial, X[:-1], U), r"states must be \(7, 2\)"),
        ((trial, X, U[:-1]), r"inputs must be \(6, 1\)"),
        (
            (trial, np.where((np.arange(7)[:, None] == 3) & [False, True], np.nan, X), U),
            r"not finite at step 3 \(row 3 of the log\): v = nan",
        ),
        ((trial, X + 1e4, U), "far outside its bounds"),
        ((trial, X, U + 1e3), "outside its bounds"),
        ((0.7, X, U), "a Trial or its integer id"),
        ((trial, [*X[:2].tolist(), ["x", 0.0], *X[3:].tolist()], U), "states holds a value that"),
        ((trial, X, U, None, -np.ones(6)), "violations cannot be negative; step 0"),
        (
            (trial, X, U, np.where(np.arange(6) == 4, np.nan, 1.0)),
            r"stage_costs .* at step 4 \(row 4 of the log's column 'stage_cost'\)",
        ),
        (
            (trial, pd.DataFrame({"p": [*X[:6, 0], "abc"], "v": X[:, 1], "f": [*U[:, 0], np.nan]})),
            "column 'p' holds a value that is not a number",
        ),
        (
            (
                trial,
                pd.DataFrame({"p": X[:, 0], "v": X[:, 1]}),
            ),
            "no column 'f'",
        ),
    ]
    for args, message in cases:
        with pytest.raises(TunerError, match=message):
            tuner.tell(*args)
        assert ckpt.read_bytes() == before  # nothing recorded changed
    tuner.tell(trial, X, U)
    with pytest.raises(TunerError, match="trial 0 was told already"):
        tuner.tell(trial, X, U)
    with pytest.raises(TunerError, match="no trial is pending"):
        tuner.tell(1, X, U)


def test_an_interrupted_tell_leaves_the_trial_pending(lq_tuner, monkeypatch):
    """An interrupt (or an error) inside tell, after the learner has seen the episode: the
    tuner is back where it was after the ask, the trial can be told again, and what is
    recorded is what an uninterrupted tell records."""
    tuner, trial = lq_tuner
    X, U = _episode(tuner, trial)
    from mpcmobo.experiment.job import Job

    original = Job._evaluate

    def interrupted(self, *args):
        raise KeyboardInterrupt

    monkeypatch.setattr(Job, "_evaluate", interrupted)
    with pytest.raises(KeyboardInterrupt):
        tuner.tell(trial, X, U)
    monkeypatch.setattr(Job, "_evaluate", original)
    assert tuner.episodes == 0 and tuner.status()["pending"] == 0
    row = tuner.tell(trial, X, U)
    assert row.episode == 0 and tuner.ask().id == 1
    reloaded = Tuner.load(tuner.run_dir.path)
    assert reloaded.episodes == 1 and reloaded.ask().id == 1


def test_the_episode_starts_where_the_log_does(tmp_path):
    """Random starts: a log that starts away from the trial's x0 is recorded from its own
    first state (x0, and the start covariate of the learners' tests, are that state's); one
    within START_TOLERANCE of x0 keeps x0; the episode's predicted cost (the exploration
    budget's) is from the logged start. Cycled starts compare thetas from the same starts: a
    log that starts elsewhere is refused, unless told with force (a noisy measurement of the
    trial's start: the episode keeps the trial's x0)."""
    for mode in ("random", "cycle"):
        tuner = Tuner("lq", "bo", tmp_path / mode, episodes=3, steps=6, start_mode=mode)
        trial = tuner.ask()
        near, U = _episode(tuner, trial, trial.x0 + 0.01 * tuner.system.x_scale)
        elsewhere, U_elsewhere = _episode(tuner, trial, trial.x0 + 0.5 * tuner.system.x_scale)
        if mode == "cycle":
            with pytest.raises(TunerError, match="must start at its trial's x0.*--force") as err:
                tuner.tell(trial, elsewhere, U_elsewhere)
            said = str(err.value)  # the start first: the other checks' findings follow from it
            assert said.startswith("trial 0's log is refused (nothing is recorded; the trial")
            also = said.find("The checks also found")
            assert also == -1 or said.index("it starts at") < also
            row = tuner.tell(trial, elsewhere, U_elsewhere, force=True)
            np.testing.assert_array_equal(row.x0, trial.x0)
            assert "start" in tuner.status()["trials"][0]["forced"]
            trial = tuner.ask()
            near, U = _episode(tuner, trial, trial.x0 + 0.01 * tuner.system.x_scale)
            row = tuner.tell(trial, near, U)
            np.testing.assert_array_equal(row.x0, trial.x0)
            continue
        run = tuner.job.run
        deployed = np.asarray(tuner.job.pending["deployed"], float)
        # the budget's prediction of the episode, from where it started
        expected = run.start_cost(
            elsewhere[0], trial.theta, run.prediction_params(deployed), trial.noise
        )
        planned = tuner.job.pending["predicted_cost"]
        row = tuner.tell(trial, elsewhere, U_elsewhere)
        np.testing.assert_array_equal(row.x0, elsewhere[0])
        assert row.predicted_cost == pytest.approx(expected) and expected != planned
        trial = tuner.ask()
        near, U = _episode(tuner, trial, trial.x0 + 0.01 * tuner.system.x_scale)
        row = tuner.tell(trial, near, U)
        np.testing.assert_array_equal(row.x0, trial.x0)
        rows = pd.read_parquet(tmp_path / mode / "episodes.parquet")
        assert rows.start_cost.nunique() == 2


def test_a_cycle_of_given_starts_is_run_in_order_and_survives_a_load(tmp_path):
    """``cycle_starts`` (a batch plant's recipes): the trials start from them in turn, also
    after a load; their number is the cycle's (the status's start index); a study's episodes
    start from them too, for every seed."""
    recipes = [[1.5, -0.5], [-1.0, 0.25], [0.0, 0.75]]
    tuner = Tuner("lq", "bo", tmp_path / "t", episodes=5, steps=6, cycle_starts=recipes)
    assert tuner.settings.n_cycle_starts == 3
    starts = []
    for k in range(4):
        if k == 2:
            tuner = Tuner.load(tmp_path / "t")
        trial = tuner.ask()
        starts.append(trial.x0.tolist())
        X, U = _episode(tuner, trial, trial.x0)
        tuner.tell(trial, X, U)
    assert starts == [*recipes, recipes[0]]
    assert [t["start"] for t in tuner.status()["trials"]] == [0, 1, 2, 0]
    settings = load_settings(
        None,
        system={"name": "lq"},
        learners=["identify"],
        seeds=[0, 1],
        episodes=3,
        steps=6,
        workers=1,
        cycle_starts=recipes,
        evaluation={"n_starts": 2},
    )
    run_study(settings, tmp_path / "study")
    rows = pd.read_parquet(tmp_path / "study" / "episodes.parquet")
    for _, job in rows.groupby("seed"):
        assert [list(x) for x in job.sort_values("episode").x0] == recipes


def test_a_tuner_is_extended_not_shortened_and_not_run_by_mpcmobo_run(tmp_path):
    """A spent budget says how to extend it; Tuner.load(out, episodes=N) and mpcmobo ask
    --episodes N extend it, a smaller one is refused; the flags that make a tuner are refused
    on an existing one; mpcmobo run --resume refuses a tuner's directory (its trials run on the
    plant); a new Tuner refuses a directory that holds one, and per-study settings."""
    out = tmp_path / "t"
    tuner = Tuner("lq", "bo", out, episodes=1, steps=6)
    trial = tuner.ask()
    tuner.tell(trial, *_episode(tuner, trial))
    with pytest.raises(TunerError, match=r"budget of 1 trials is spent.*episodes=N"):
        tuner.ask()
    with pytest.raises(TunerError, match="extended, not shortened"):
        Tuner.load(out, episodes=0)
    assert Tuner.load(out, episodes=2).ask().id == 1
    assert Tuner.load(out).settings.episodes == 2  # saved
    runner = CliRunner()
    res = runner.invoke(app, ["ask", str(out), "--learner", "mpc-rl"])
    assert res.exit_code == 2 and "--learner applies only when one is made" in res.output
    res = runner.invoke(app, ["ask", str(out), "--episodes", "3"])
    assert res.exit_code == 0 and json.loads(res.output)["id"] == 1, res.output
    assert Tuner.load(out).settings.episodes == 3
    res = runner.invoke(app, ["run", "--resume", "--out", str(out), "-q"])
    assert res.exit_code != 0 and "holds a tuner" in " ".join(res.output.split()), res.output
    assert pd.read_parquet(out / "episodes.parquet").shape[0] == 1  # nothing run
    with pytest.raises(TunerError, match="holds a run already: continue it with Tuner.load"):
        Tuner("lq", "bo", out)
    with pytest.raises(TunerError, match="give learner= and seed=, not seeds"):
        Tuner("lq", "bo", tmp_path / "s", seeds=[1, 2])


def test_a_tuner_with_no_told_trial_is_extended(tmp_path):
    """A budget extended before the first tell (trial 0 asked, pending): the tuner loads with
    the larger budget, gives the same pending trial, and goes on."""
    out = tmp_path / "t"
    tuner = Tuner("lq", "bo", out, episodes=1, steps=6)
    trial = tuner.ask()
    extended = Tuner.load(out, episodes=2)
    again = extended.ask()
    assert again.id == 0 and np.array_equal(again.theta, trial.theta)
    assert Tuner.load(out).settings.episodes == 2
    res = CliRunner().invoke(app, ["ask", str(out), "--episodes", "3"])
    assert res.exit_code == 0 and json.loads(res.output)["id"] == 0, res.output
    extended = Tuner.load(out)
    extended.tell(again, *_episode(extended, again))
    assert extended.ask().id == 1 and extended.settings.episodes == 3


def test_a_tuner_that_cannot_be_built_leaves_nothing(tmp_path):
    """A system the settings cannot build (an unknown identified parameter) fails before a
    tuner exists: the directory is left as it was, in Python and on the command line."""
    with pytest.raises(Exception, match="nosuch"):
        Tuner({"name": "lq", "identify": ["nosuch"]}, "bo", tmp_path / "t", episodes=2)
    assert not (tmp_path / "t").exists()
    (tmp_path / "empty").mkdir()
    cfg = tmp_path / "bad.toml"
    cfg.write_text('[system]\nname = "lq"\nidentify = ["nosuch"]\n')
    res = CliRunner().invoke(app, ["ask", str(tmp_path / "empty"), "-c", str(cfg)])
    assert res.exit_code == 2 and "nosuch" in res.output, res.output
    assert list((tmp_path / "empty").iterdir()) == []


def test_status_counts_every_change_and_evaluates_only_the_deployed_theta(tmp_path):
    """mpc-rl deploying its iterate (the deployed theta changes at every tell, the first from
    theta0): status counts both changes, and with the second tell not evaluated (every 2nd
    episode is) it gives no J_eval rather than the previous theta's."""
    out = tmp_path / "t"
    tuner = Tuner(
        {"name": "lq", "identify": False},
        "mpc-rl",
        out,
        episodes=3,
        steps=6,
        learner_options={"mpc-rl": {"deploy": "iterate"}},
        evaluation={"n_starts": 2, "eval_every": 2},
    )
    for _ in range(2):
        trial = tuner.ask()
        tuner.tell(trial, *_episode(tuner, trial))
    st = tuner.status()
    assert st["changes_of_deployed"] == 2 and st["J_eval"] is None
    res = CliRunner().invoke(app, ["status", str(out)])
    assert "changed twice" in res.output and "deployed theta not evaluated yet" in res.output


def test_a_dataframe_log_with_measured_costs(lq_tuner):
    """A log as a DataFrame with stage_cost and violation columns: those are what the episode
    records (the mean stage cost is theirs)."""
    tuner, trial = lq_tuner
    X, U = _episode(tuner, trial)
    df = pd.DataFrame(
        {
            "p": X[:, 0],
            "v": X[:, 1],
            "f": [*U[:, 0], np.nan],
            "stage_cost": [2.0] * 7,
            "violation": [0.5] * 7,
        }
    )
    row = tuner.tell(trial, df)
    assert row.mean_stage_cost == pytest.approx(2.0) and row.violation == pytest.approx(3.0)


def test_status_warns_of_an_identified_parameter_held_by_its_bounds(tmp_path):
    """The identify learner on lq through ask/tell, with bounds of e^(+-0.2) that do not hold
    the plant's values: after a told trial, ``mpcmobo status`` names the parameters whose fit
    sits on a bound."""
    cfg = tmp_path / "narrow.toml"
    cfg.write_text('[system]\nname = "lq"\nmodel_log_range = 0.2\n')
    tuner = Tuner(None, "identify", tmp_path / "t", config=cfg, episodes=2, steps=20)
    trial = tuner.ask()
    tuner.tell(trial, *_episode(tuner, trial))
    res = CliRunner().invoke(app, ["status", str(tmp_path / "t")])
    assert res.exit_code == 0, res.output
    assert "'damping' ends on its upper bound" in res.output
    assert "identify seed 0" in res.output


def test_status_reports_the_identified_model(tmp_path):
    """With identification, ``status`` reports the last fit: per parameter the nominal value,
    the estimate (lq's plant values after one episode) and its standard deviation, and the
    fit's one-step error on held-out transitions far below the nominal model's; without it,
    none."""
    tuner = Tuner("lq", "bo", tmp_path / "t", episodes=3, steps=20)
    assert tuner.status()["identification"] is None  # no fit before a told trial
    trial = tuner.ask()
    tuner.tell(trial, *_episode(tuner, trial))
    ident = tuner.status()["identification"]
    system = tuner.system
    assert list(ident["parameters"]) == list(system.param_names)
    assert ident["transitions"] == 20 and ident["refit_growth"] == REFIT_GROWTH
    for name, true, nominal in zip(
        system.param_names, system.true_params, system.models["imperfect"]
    ):
        p = ident["parameters"][name]
        assert p["nominal"] == pytest.approx(nominal)
        assert p["estimate"] == pytest.approx(true, rel=0.02), name  # the prior pulls a little
        assert 0 < p["std"] < 0.01 * abs(true)
    assert ident["holdout_error"] < 0.1 * ident["nominal_error"]
    res = CliRunner().invoke(app, ["status", str(tmp_path / "t")])
    assert res.exit_code == 0, res.output
    assert "identified model (the last fit)" in res.output
    assert "fitted on 20 transitions" in res.output
    off = Tuner({"name": "lq", "identify": False}, "bo", tmp_path / "off", episodes=2, steps=20)
    trial = off.ask()
    off.tell(trial, *_episode(off, trial))
    assert off.status()["identification"] is None
    res = CliRunner().invoke(app, ["status", str(tmp_path / "off")])
    assert res.exit_code == 0 and "identified model" not in res.output, res.output


def test_the_command_line_asks_tells_and_reports(tmp_path):
    runner = CliRunner()
    d = tmp_path / "tun"
    res = runner.invoke(app, ["ask", str(d), "--system", "lq", "--learner", "bo", "-n", "2"])
    assert res.exit_code == 0, res.output
    trial = json.loads(res.output)
    assert trial["id"] == 0 and set(trial["theta"]) >= {"Q_p", "R_f"}
    assert (d / "trials" / "0" / "controller.casadi").exists()
    tuner = Tuner.load(d)
    X, U = _episode(tuner, tuner.ask())
    write_log(tmp_path / "ep.csv", X, U, tuner.system)
    res = runner.invoke(app, ["tell", str(d), "0", str(tmp_path / "ep.csv")])
    assert res.exit_code == 0 and "trial 0 told" in res.output, res.output
    res = runner.invoke(app, ["tell", str(d), "0", str(tmp_path / "ep.csv")])
    assert res.exit_code == 2 and "told already" in res.output
    res = runner.invoke(app, ["status", str(d)])
    assert res.exit_code == 0 and "1 of 2 trials told" in res.output and "Q_p" in res.output
    assert pd.read_parquet(d / "episodes.parquet").shape[0] == 1


def test_a_tell_killed_between_its_checkpoint_and_its_records_is_repaired_at_the_next_load(
    lq_tuner, monkeypatch
):
    """A tell stopped after the learner's state was saved (the trial told) and before the
    records and ``status.json`` were written from it: the next load writes them, so the
    records, the status file and the checkpoint agree (as after a tell that ended)."""
    import mpcmobo.experiment.tuner as tuner_module

    tuner, trial = lq_tuner
    out = tuner.run_dir.path

    def killed(*args, **kwargs):
        raise SystemExit("killed here")  # as kill -9 after the checkpoint

    monkeypatch.setattr(tuner_module, "write_records", killed)
    monkeypatch.setattr(Tuner, "_write_status", lambda self: None)  # nothing runs after a kill
    with pytest.raises(SystemExit):
        tuner.tell(trial, *_episode(tuner, trial))
    monkeypatch.undo()
    assert not (out / "episodes.parquet").exists()  # no records of the told trial
    assert json.loads((out / "status.json").read_text())["told"] == 0
    loaded = Tuner.load(out)
    assert loaded.episodes == 1
    assert len(pd.read_parquet(out / "episodes.parquet")) == 1
    assert json.loads((out / "status.json").read_text())["told"] == 1
    assert loaded.ask().id == 1
