"""Taking a told trial back (Tuner.retract, mpcmobo retract) and what status says: a retract
followed by the same further trials records what a tuner that never saw the retracted trial
records; the retracted records are kept; status lists the trials, their plant cost, the
quarantined ones and what to do, in Python, as JSON, in status.json and as text."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest
from test_tuner_checks import episode
from typer.testing import CliRunner

from mpcmobo.cli import app
from mpcmobo.experiment.tuner import LogQuarantined, Tuner, TunerError

SETTINGS = {"episodes": 4, "steps": 12, "start_mode": "cycle", "n_cycle_starts": 2}


def _records(path):
    """episodes.parquet without the wall times."""
    df = pd.read_parquet(path / "episodes.parquet")
    return df.drop(columns=[c for c in df.columns if c.endswith("time_s")])


def _told(tuner, trials):
    for _ in range(trials):
        trial = tuner.ask()
        tuner.tell(trial, *episode(tuner, trial))


def test_a_retract_gives_the_records_of_a_tuner_that_never_saw_the_trial(tmp_path):
    """Trial 1 told with an operator's override accepted by force, then retracted: asked
    again it is the same trial, and after the same further trials the records equal those of
    a tuner that was told the true log at once. The retracted record and log are kept."""
    clean = Tuner("lq", "mpc-rl", tmp_path / "clean", **SETTINGS)
    _told(clean, 3)
    tuner = Tuner("lq", "mpc-rl", tmp_path / "t", **SETTINGS)
    _told(tuner, 1)
    trial = tuner.ask()
    bad = episode(tuner, trial, override=(range(2, 7), [2.5]))
    with pytest.raises(LogQuarantined):
        tuner.tell(trial, *bad)
    tuner.tell(trial, *bad, force=True)
    asked = tuner.ask()  # trial 2, proposed after the bad log
    with pytest.raises(TunerError, match=r"trial 1 has not been told|told after"):
        tuner.retract(0)  # trial 1 was told after it
    assert tuner.retract(1) == [1]
    assert tuner.status()["pending"] == 1 and tuner.episodes == 1
    again = Tuner.load(tuner.run_dir.path).ask()
    assert again.id == 1 and np.array_equal(again.theta, trial.theta)
    assert np.array_equal(again.noise, trial.noise) and asked.id == 2
    tuner = Tuner.load(tuner.run_dir.path)
    tuner.tell(again, *episode(tuner, again))
    _told(tuner, 1)
    a, b = _records(tmp_path / "t"), _records(tmp_path / "clean")
    pd.testing.assert_frame_equal(a, b)
    kept = json.loads((tmp_path / "t" / "retracted" / "trial-1.json").read_text())
    assert kept["forced"] and kept["record"]["episode"] == 1
    retracted = pd.read_parquet(tmp_path / "t" / "retracted" / "episodes.parquet")
    assert list(retracted.episode) == [1] and "retracted_at" in retracted.columns
    np.testing.assert_array_equal(
        pd.read_parquet(tmp_path / "t" / "retracted" / "trial-1.parquet")[["f"]].to_numpy()[:-1],
        bad[1],
    )


def test_retracting_a_trial_with_later_ones(tmp_path):
    """Retracting trial 0 after trial 1 was told takes both back when asked to (they are kept),
    and the first trial is pending again; an untold trial cannot be retracted."""
    tuner = Tuner("lq", "mpc-rl", tmp_path / "t", **SETTINGS)
    _told(tuner, 2)
    with pytest.raises(TunerError, match="trial 1 was told after trial 0.*later=True"):
        tuner.retract(0)
    with pytest.raises(TunerError, match="trial 5 has not been told"):
        tuner.retract(5)
    res = CliRunner().invoke(app, ["retract", str(tmp_path / "t"), "0", "--with-later"])
    assert res.exit_code == 0 and "retracted trials 0, 1" in res.output, res.output
    tuner = Tuner.load(tmp_path / "t")
    assert tuner.episodes == 0 and tuner.status()["pending"] == 0
    assert not (tmp_path / "t" / "episodes.parquet").exists() or _records(tmp_path / "t").empty
    assert sorted(p.name for p in (tmp_path / "t" / "retracted").glob("*.json")) == [
        "trial-0.json",
        "trial-1.json",
    ]
    out = tmp_path / "theta.casadi"
    res = CliRunner().invoke(
        app, ["export", str(tmp_path / "t"), "--theta", "1", "--out", str(out)]
    )
    said = " ".join(res.output.split())
    assert res.exit_code == 2 and "no trial 1: the job has no told trial" in said, said
    assert "(trial 1 was retracted: its record is kept in" in said and not out.exists()


def test_a_trial_retracted_twice_keeps_both_logs(tmp_path):
    """Told, retracted, told again with another log and retracted again: both logs and both
    records are kept (the earlier as ``trial-<id>-1``), nothing overwritten."""
    tuner = Tuner("lq", "mpc-rl", tmp_path / "t", **SETTINGS)
    logs = []
    for k in range(2):
        trial = tuner.ask()
        states, inputs = episode(tuner, trial)
        logs.append(states)
        tuner.tell(trial, states * (1 + 1e-3 * k), inputs, force=True)
        assert tuner.retract(trial) == [0]
    kept = tmp_path / "t" / "retracted"
    assert sorted(p.name for p in kept.glob("*.json")) == ["trial-0-1.json", "trial-0.json"]
    first = pd.read_parquet(kept / "trial-0-1.parquet")
    second = pd.read_parquet(kept / "trial-0.parquet")
    assert json.loads((kept / "trial-0-1.json").read_text())["log"] == "trial-0-1.parquet"
    np.testing.assert_allclose(second.iloc[:, :2].to_numpy() / first.iloc[:, :2].to_numpy(), 1.001)
    assert len(pd.read_parquet(kept / "episodes.parquet")) == 2


def test_status_lists_the_trials_and_says_what_to_do(tmp_path):
    out = tmp_path / "t"
    tuner = Tuner(
        {"name": "lq", "identify": False},
        "mpc-rl",
        out,
        episodes=3,
        steps=12,
        learner_options={"mpc-rl": {"deploy": "iterate"}},
    )
    _told(tuner, 2)
    trial = tuner.ask()
    with pytest.raises(LogQuarantined):
        tuner.tell(trial, *episode(tuner, trial, override=(range(2, 7), [2.5])))
    st = tuner.status()
    assert [t["id"] for t in st["trials"]] == [0, 1] and st["told"] == 2
    rows = pd.read_parquet(out / "episodes.parquet")
    assert [t["plant_cost"] for t in st["trials"]] == pytest.approx(list(rows.mean_stage_cost))
    assert st["plant_cost"] == pytest.approx(rows.mean_stage_cost.sum())
    excess = [t["excess_cost"] for t in st["trials"]]
    assert excess == pytest.approx(list(rows.excess_cost))
    assert st["excess_cost"] == pytest.approx(rows.excess_cost.sum())
    assert st["trials"][0]["role"] == "deployed"  # theta0, deployed before it
    assert st["trials"][0]["start"] == 0 and st["trials"][1]["start"] == 1
    assert st["quarantined"] == [2] and st["pending"] == 2
    assert st["recommendation"]["action"] == "continue"
    assert "quarantined" in st["recommendation"]["reason"]
    assert json.loads((out / "status.json").read_text())["quarantined"] == [2]
    res = CliRunner().invoke(app, ["status", str(out), "--json"])
    assert res.exit_code == 0 and json.loads(res.output)["trials"][1]["id"] == 1, res.output
    res = CliRunner().invoke(app, ["status", str(out)])
    assert res.exit_code == 0 and "quarantined logs" in res.output, res.output
    assert "plant cost of tuning" in res.output and "next: continue" in res.output
    tuner.tell(trial, force=True)
    st = tuner.status()
    assert st["recommendation"]["action"] == "stop" and "budget" in st["recommendation"]["reason"]
    assert json.loads((out / "status.json").read_text())["told"] == 3
