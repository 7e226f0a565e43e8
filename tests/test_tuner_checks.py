"""A told log is checked before it is believed (mpcmobo.experiment.checks): a state in the
wrong unit, two swapped rows, another trial's log, an operator override of 5 steps and a log in
reverse time order are each refused or quarantined with the problem named, under both start
modes, and nothing recorded is lost; a quarantined log stays on disk and ``force`` accepts it;
an episode the model explains far worse than the episodes before is quarantined."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pandas as pd
import pytest

from mpcmobo.experiment import checks
from mpcmobo.experiment.plantlog import PlantLog
from mpcmobo.experiment.tuner import LogQuarantined, Tuner, TunerError
from mpcmobo.systems.plant import SystemPlant

MODES = ("cycle", "random")


def episode(tuner, trial, x0=None, override=None, plant_system=None):
    """The user's loop on the simulated plant (``plant_system``'s equations, default the
    tuner's): the trial's policy plus its noise, clipped; ``override``: (steps, input) an
    operator applies instead."""
    system = tuner.system
    plant = SystemPlant(system if plant_system is None else plant_system)
    trial.restart()
    x, _ = plant.reset(seed=0, options={"x0": trial.x0 if x0 is None else x0})
    states, inputs = [x], []
    for k in range(trial.steps):
        u = np.clip(trial.policy(x) + trial.noise[k], system.u_lb, system.u_ub)
        if override is not None and k in override[0]:
            u = np.asarray(override[1], float)
        x, *_ = plant.step(u)
        states.append(x)
        inputs.append(u)
    return np.array(states), np.array(inputs)


def _recorded(tuner):
    """What is recorded: the checkpoint's bytes and the rows of episodes.parquet."""
    ckpt = next((tuner.run_dir.path / "jobs").glob("*/checkpoint.pkl")).read_bytes()
    path = tuner.run_dir.path / "episodes.parquet"
    rows = pd.read_parquet(path).shape[0] if path.exists() else 0
    return ckpt, rows


@pytest.mark.parametrize("mode", MODES)
def test_bad_logs_are_refused_or_quarantined_with_the_problem_named(tmp_path, mode):
    tuner = Tuner("lq", "mpc-rl", tmp_path / mode, episodes=4, steps=20, start_mode=mode)
    first = tuner.ask()
    X0, U0 = episode(tuner, first)
    tuner.tell(first, X0, U0)
    trial = tuner.ask()
    X, U = episode(tuner, trial)
    assert np.any(trial.noise != 0)
    swapped = X.copy(), U.copy()
    for a in swapped:
        a[[5, 6]] = a[[6, 5]]
    override = episode(tuner, trial, override=(range(8, 13), [1.0]))
    cases = {
        "swapped": (swapped, r"steps [456-]+\W.*rows out of order"),
        "override": (override, r"at steps 8-12: an operator override"),
        "reversed": ((X[::-1], U[::-1]), "reverse time order"),
        "another trial's": (episode(tuner, first, x0=trial.x0), "another trial's log"),
    }
    before, quarantined = _recorded(tuner), 0
    for name, (log, message) in cases.items():
        with pytest.raises(TunerError, match=message) as err:
            tuner.tell(trial, *log)
        assert _recorded(tuner) == before, name  # nothing recorded changes
        assert tuner.status()["pending"] == trial.id, name
        if isinstance(err.value, LogQuarantined):  # kept, with the reasons
            kept = json.loads(err.value.path.with_suffix(".json").read_text())
            assert kept["status"] == "quarantined" and kept["problems"], name
            assert pd.read_parquet(err.value.path).shape[0] == len(X), name
            assert tuner.status()["quarantined"] == [trial.id]
            quarantined += 1
        else:  # cycled starts: it does not start at the trial's x0 either
            assert mode == "cycle" and "must start at its trial's x0" in str(err.value), name
    with pytest.raises(TunerError, match="this log is trial 0's, told already"):
        tuner.tell(trial, X0, U0)
    table = PlantLog(X, U).frame(tuner.system)  # a table sorted the wrong way
    with pytest.raises(TunerError, match="first row has no inputs .* reverse time order"):
        tuner.tell(trial, table.iloc[::-1].reset_index(drop=True))
    late = table.assign(time=np.arange(len(X)) * 0.1)  # a historian's: the inputs a row late
    late[list(tuner.system.input_names)] = late[list(tuner.system.input_names)].shift(1)
    with pytest.raises(TunerError, match="time increases: the inputs logged one row late"):
        tuner.tell(trial, late)
    timed = table.assign(time=np.arange(len(X)) * 0.1)
    timed.loc[[3, 4], "time"] = timed.loc[[4, 3], "time"].to_numpy()
    with pytest.raises(TunerError, match="out of time order at rows 4"):
        tuner.tell(trial, timed)
    assert _recorded(tuner) == before
    quarantined += 1
    kept = sorted(p.name for p in (tuner.run_dir.path / "quarantine").glob("*.parquet"))
    assert len(kept) == quarantined >= 2, kept  # every quarantined log is kept
    row = tuner.tell(trial, X, U)  # the true log is believed
    assert row.episode == trial.id and tuner.status()["quarantined"] == []
    assert json.loads((tuner.run_dir.path / "status.json").read_text())["told"] == 2


@pytest.mark.parametrize("mode", MODES)
def test_a_state_in_the_wrong_unit_is_refused_even_with_force(tmp_path, mode):
    """The CSTR's concentration logged ten times too large, or its temperature (kelvin) in
    degrees Celsius: refused under both start modes, the column, the unit and the conversion
    named, before the MPC is replayed; not advised to be forced, and ``force=True`` refuses it
    too: nothing is recorded or quarantined, the trial stays pending, and the log in the
    system's units is then believed."""
    tuner = Tuner(
        "cstr",
        "mpc-rl",
        tmp_path / mode,
        episodes=2,
        steps=8,
        start_mode=mode,
        evaluation={"n_starts": 1},
    )
    trial = tuner.ask()
    X, U = episode(tuner, trial)
    ten, celsius = X.copy(), X.copy()
    ten[:, 1] *= 10
    celsius[:, 2] -= 273.15
    cases = (
        (ten, r"state Ca .* divided by 10.* a unit error.* convert the column \(divided by 10\)"),
        (celsius, r"T looks like Celsius for kelvin .* convert the column \(plus 273.15\)"),
    )
    before = _recorded(tuner)
    for log, message in cases:
        for force in (False, True):
            with pytest.raises(TunerError, match=message) as err:
                tuner.tell(trial, log, U, force=force)
            assert not isinstance(err.value, LogQuarantined), force
            assert "--force (force=True)" not in str(err.value), force
            assert "--force does not accept a log with a state in the wrong unit" in str(err.value)
            assert _recorded(tuner) == before, force
            st = tuner.status()
            assert st["quarantined"] == [] and st["pending"] == trial.id, force
    assert not list((tuner.run_dir.path / "quarantine").glob("*.parquet"))
    assert tuner.tell(trial, X, U).episode == trial.id


def test_every_temperature_scale_is_named_with_its_conversion():
    """kelvin, Celsius and Fahrenheit each for each other: the table holds every pair both
    ways, each conversion maps the freezing and boiling points of water, the pair's two are
    inverse, and a column logged in each scale is named by its own (Fahrenheit for kelvin:
    "(T - 32) 5/9 + 273.15")."""
    points = {"kelvin": (273.15, 373.15), "Celsius": (0.0, 100.0), "Fahrenheit": (32.0, 212.0)}
    table = {looks: (convert, words) for looks, convert, words in checks.TEMPERATURE_SCALES}
    pairs = {(a, b) for a in points for b in points if a != b}
    assert set(table) == {f"{a} for {b}" for a, b in pairs}
    for a, b in pairs:
        convert = table[f"{a} for {b}"][0]
        back = table[f"{b} for {a}"][0]
        np.testing.assert_allclose(convert(np.array(points[a])), points[b], atol=1e-9)
        t = np.linspace(-50.0, 500.0, 7)
        np.testing.assert_allclose(back(convert(t)), t, atol=1e-9)
    from mpcmobo.systems import get_system

    cstr = get_system("cstr")  # T in kelvin, its box [400, 480]
    X = np.tile(cstr.x_ref, (5, 1))
    X[:, 2] += np.linspace(-10.0, 10.0, 5)
    fahrenheit = X.copy()
    fahrenheit[:, 2] = (X[:, 2] - 273.15) * 9 / 5 + 32
    (found,) = checks.box_problems(cstr, fahrenheit, start=X[0])
    assert "T looks like Fahrenheit for kelvin ((T - 32) 5/9 + 273.15" in found.message
    assert not found.forceable


def test_a_unit_error_inside_the_box_is_named_by_the_start(tmp_path):
    """A state logged ten times too large that stays inside its box (cycled starts): its first
    value is the trial's start times 10, and the refusal says so first."""
    tuner = Tuner("lq", "mpc-rl", tmp_path / "t", episodes=2, steps=10, start_mode="cycle")
    trial = tuner.ask()
    X, U = episode(tuner, trial)
    j = int(np.argmin(np.max(np.abs(X), axis=0) / tuner.system.x_ub))
    assert np.all(np.abs(10 * X[:, j]) < tuner.system.x_ub[j])  # inside the box at 10x
    X[:, j] *= 10
    name = tuner.system.state_names[j]
    with pytest.raises(TunerError, match=rf"^the log's {name} looks 10 times too large"):
        tuner.tell(trial, X, U)


def test_force_accepts_the_quarantined_log(tmp_path):
    """``force=True`` without a log tells the quarantined one; the quarantine keeps it, marked
    accepted, and the status's trial says what it was accepted despite; a trial without a
    quarantined log has nothing to force."""
    tuner = Tuner("lq", "mpc-rl", tmp_path / "t", episodes=3, steps=20, start_mode="random")
    trial = tuner.ask()
    with pytest.raises(TunerError, match="no quarantined log"):
        tuner.tell(trial, force=True)
    X, U = episode(tuner, trial, override=(range(3, 8), [2.5]))
    with pytest.raises(LogQuarantined, match="steps 3-7") as err:
        tuner.tell(trial, X, U)
    row = Tuner.load(tuner.run_dir.path).tell(trial.id, force=True)
    assert row.episode == 0
    kept = json.loads(err.value.path.with_suffix(".json").read_text())
    assert kept["status"] == "accepted (force)"
    reloaded = Tuner.load(tuner.run_dir.path)
    assert reloaded.episodes == 1 and reloaded.status()["quarantined"] == []
    np.testing.assert_array_equal(reloaded.files.told(0)["log"].inputs, U)
    assert reloaded.files.told(0)["forced"]
    (told,) = reloaded.status()["trials"]
    found = sorted({p.check for p in err.value.problems})
    assert told["forced"] == found and "accepted with --force despite" in told["verdict"]


def test_an_episode_the_model_cannot_explain_is_quarantined(tmp_path):
    """After three told episodes, a log of another plant (the inputs are the trial's): the
    identified model explains it far worse than the episodes before."""
    tuner = Tuner("lq", "mpc-rl", tmp_path / "t", episodes=5, steps=20, start_mode="random")
    for _ in range(3):
        trial = tuner.ask()
        tuner.tell(trial, *episode(tuner, trial))
    trial = tuner.ask()
    other = replace(tuner.system, true_params=tuner.system.true_params * np.array([3, 0.3, 2]))
    with pytest.raises(LogQuarantined, match=r"identified model explains this episode far worse"):
        tuner.tell(trial, *episode(tuner, trial, plant_system=other))
    tuner.tell(trial, *episode(tuner, trial))


def test_the_checks_on_their_own():
    """Steps are named in runs; a time column that decreases is a reversed log; a column a
    power of ten too small is named too."""
    assert checks.describe_steps([9, 3, 4, 5]) == "3-5, 9"
    from mpcmobo.systems import get_system

    cstr = get_system("cstr")
    X = np.tile(cstr.x_ref, (5, 1))
    U = np.tile(cstr.u_ref, (4, 1))
    found = checks.order_problems(cstr, X, U, cstr.models["imperfect"], time=[4, 3, 2, 1, 0])
    assert found and "reverse time order" in found[0].message
    (found,) = checks.order_problems(cstr, X, U, cstr.models["imperfect"], time=[0, 1, 3, 2, 4])
    assert "out of time order at rows 3" in found.message and found.steps == (3,)
    assert checks.order_problems(cstr, X, U, cstr.models["imperfect"], time=[0, 1, 1, 2, 3]) == []
    X[:, 0] /= 100  # V in hectolitres
    (found,) = checks.box_problems(cstr, X)
    assert "multiplied by 100" in found.message and found.steps == (0, 1, 2, 3, 4)
    celsius = np.tile(cstr.x_ref, (5, 1))
    celsius[:, 2] -= 273.15  # the CSTR's T (kelvin) logged in degrees Celsius
    (found,) = checks.box_problems(cstr, celsius, start=cstr.x_ref)
    assert "T looks like Celsius for kelvin (plus 273.15" in found.message
    (found,) = checks.box_problems(cstr, celsius)  # without the start: the box alone
    assert "far outside its bounds" in found.message
    assert checks.box_problems(cstr, np.tile(cstr.x_ref, (5, 1))) == []
    # mostly small values a thousand times too large: 10 brings 90% of them into [0, 30], 100
    # and 1000 all of them; the trial's start tells 1000
    x = 1000 * np.array([2.2, 0.5, *[0.2] * 18])
    assert checks.unit_factor(x, 0.0, 30.0, 30.0) == 100.0
    assert checks.unit_factor(x, 0.0, 30.0, 30.0, start=2.2) == 1000.0
    assert checks.start_factor(22.19, 2.219) == 10.0
    assert checks.start_factor(2.3, 2.219) is None and checks.start_factor(-22.19, 2.219) is None


def test_an_episode_run_on_the_exported_controller_is_the_trials(tmp_path, monkeypatch):
    """``controller.casadi`` (IPOPT from its last solution) may stop at another local minimum
    than the MPC's own solve, or fail where the user applies a fallback: a log whose inputs are
    the exported controller's plus the noise, or anything where it failed, is the trial's; an
    input that is neither is still an override. On `lq` both controllers agree, so the exported
    controller's other minimum at steps 3-6 and its failure at step 8 are stood in for."""
    from mpcmobo.mpc.export import controller_inputs

    tuner = Tuner("lq", "bo", tmp_path / "t", episodes=3, steps=12)
    trial = tuner.ask()
    X, U = episode(tuner, trial, override=(range(3, 7), [0.7]))
    (real,) = controller_inputs(tuner.job.run.mpc, trial.theta, X[:-1])  # no call failed
    trial.restart()
    np.testing.assert_allclose(real, np.array([trial.policy(x) for x in X[:-1]]), atol=1e-5)
    found = checks.input_problems(tuner.system, U, real, trial.noise, trial.id)
    assert found and found[0].steps == (3, 4, 5, 6)
    other = real.copy()
    other[3:7] = 0.7 - trial.noise[3:7]  # the exported controller's own minimum there
    other[8] = np.nan  # it failed: the user's fallback
    U_fallback = U.copy()
    U_fallback[8] = -0.3
    assert checks.input_problems(tuner.system, U_fallback, real, trial.noise, 0, [other]) == []
    U_fallback[10] += 0.2  # neither controller's
    (found,) = checks.input_problems(tuner.system, U_fallback, real, trial.noise, 0, [other])
    assert found.steps == (10,)
    monkeypatch.setattr(checks, "controller_inputs", lambda *args: [other])
    row = tuner.tell(trial, X, U)  # the review asks the exported controller
    assert row.episode == trial.id and tuner.status()["quarantined"] == []


def test_an_actuator_that_saturates_inside_the_bounds_is_named():
    """Inputs held at one value where the controller asked more, and never above it: an
    actuator that saturates inside the input's bounds, named as such; a constant override
    that the episode's other inputs pass is an operator's."""
    from mpcmobo.systems import get_system

    lq = get_system("lq")
    pi = np.linspace(-1.0, 3.0, 12)[:, None]  # what the controller asked
    noise = np.zeros_like(pi)
    (found,) = checks.input_problems(lq, np.minimum(pi, 2.0), pi, noise, 4)
    assert "the applied f stays at 2 where the controller asked more: an actuator" in found.message
    override = pi.copy()
    override[3:6] = 2.0  # an operator's setting; the controller's later inputs pass it
    (found,) = checks.input_problems(lq, override, pi, noise, 4)
    assert "an actuator" not in found.message and "operator override" in found.message


def sensed_episode(tuner, trial, noise, seed):
    """The user's loop on the simulated plant through a sensor of Gaussian noise ``noise``
    (a fraction of each state's x_scale): the controller is given, and the log holds, the
    measured states."""
    system = tuner.system
    plant = SystemPlant(system)
    rng = np.random.default_rng(seed)
    scale = noise * np.asarray(system.x_scale, float)
    trial.restart()
    x, _ = plant.reset(seed=0, options={"x0": trial.x0})
    y = x + scale * rng.standard_normal(system.nx)
    states, inputs = [y], []
    for k in range(trial.steps):
        u = np.clip(trial.policy(y) + trial.noise[k], system.u_lb, system.u_ub)
        x, *_ = plant.step(u)
        y = x + scale * rng.standard_normal(system.nx)
        states.append(y)
        inputs.append(u)
    return np.array(states), np.array(inputs)


def test_a_noisier_sensor_told_with_force_becomes_the_baseline(tmp_path):
    """After three episodes at a sensor noise of 0.26% of x_scale, an honest episode at 2% is
    quarantined with higher measurement noise named as a possible cause; told with force, it
    is the baseline of the model check, so the next honest episode at 2% is believed, and one
    far worse than it is still quarantined."""
    tuner = Tuner("lq", "mpc-rl", tmp_path / "t", episodes=6, steps=20, start_mode="random")
    for k in range(3):
        trial = tuner.ask()
        tuner.tell(trial, *sensed_episode(tuner, trial, 0.0026, k))
    trial = tuner.ask()
    with pytest.raises(LogQuarantined, match="more measurement noise than in the episodes told"):
        tuner.tell(trial, *sensed_episode(tuner, trial, 0.02, 3))
    tuner.tell(trial.id, force=True)
    assert tuner.status()["trials"][-1]["forced"] == ["model"]
    trial = tuner.ask()
    with pytest.raises(LogQuarantined, match="explains this episode far worse"):
        tuner.tell(trial, *sensed_episode(tuner, trial, 0.3, 4))
    row = Tuner.load(tuner.run_dir.path).tell(trial.id, *sensed_episode(tuner, trial, 0.02, 5))
    assert row.episode == trial.id


def test_a_missing_or_repeated_row_is_named_by_the_time_column(tmp_path):
    """A log with a ``time`` column: a row dropped is named by where the time step is twice
    the usual (refused, with what to do), as is a last row missing (the state after the last
    input) and a row written twice; a row written twice next to a missing one (the row count
    right, the rows between a step off) is named so, not as an operator override."""
    tuner = Tuner("lq", "mpc-rl", tmp_path / "t", episodes=2, steps=20, start_mode="random")
    trial = tuner.ask()
    X, U = episode(tuner, trial)
    table = PlantLog(X, U).frame(tuner.system).assign(time=np.arange(len(X)) * 30.0)
    cases = {
        "dropped": (table.drop(index=12), r"the log 20: a row is missing after row 11 \(the time"),
        "no last state": (table.iloc[:-1], "the state after the last input is missing"),
        "twice": (
            pd.concat([table.iloc[:6], table.iloc[[5]], table.iloc[6:]]),
            "its time repeats at row 6 .a row written twice.: drop the repeated row",
        ),
    }
    before = _recorded(tuner)
    for name, (log, message) in cases.items():
        with pytest.raises(TunerError, match=message):
            tuner.tell(trial, log.reset_index(drop=True))
        assert _recorded(tuner) == before, name
    dropped = table.drop(index=12).reset_index(drop=True)
    shifted = pd.concat([dropped.iloc[:6], dropped.iloc[[5]], dropped.iloc[6:]])
    with pytest.raises(LogQuarantined) as err:
        tuner.tell(trial, shifted.reset_index(drop=True))
    (found,) = err.value.problems
    assert found.check == "time_order" and found.steps == tuple(range(6, 13))
    assert "time repeats at row 6 (a row written twice) and a row is missing after row 12" in (
        found.message
    )
    assert "operator override" not in str(err.value)
    assert tuner.tell(trial, table).episode == trial.id
