"""mpcmobo connect against a real OPC UA server (asyncua) whose nodes are the simulated CSTR on
an accelerated clock, stepping at each write of the inputs so that a busy machine's late
period does not change the plant's response (tests/opcua_plant.py): three trials are asked,
run and told; each fault (stale data, the enable withdrawn, a refused write, a lost
connection, Ctrl-C) aborts the trial, keeps its log, tells nothing and hands the plant back
with the safe input; the next connect runs the aborted trial again. No input outside the
bounds is ever written."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from typer.testing import CliRunner

from mpcmobo.cli import app
from mpcmobo.connect import ConnectError, load_nodes, run_plant
from mpcmobo.experiment.tuner import Tuner
from mpcmobo.systems import get_system

sys.path.insert(0, str(Path(__file__).parent))
from opcua_plant import KELVIN, SimPlant, free_port, node_map  # noqa: E402

PERIOD = 0.15  # the CSTR's 3 s sampling, 20 times faster
CONFIG = """\
episodes = 8
steps = 8
[evaluation]
n_starts = 1
eval_every = 4
[exploration]
std = [40.0, 40.0]  # wide: the controller's input plus the noise often leaves the bounds
budget = inf  # the loop over OPC UA, not the budget: every trial runs the learner's theta
"""
SAFE = np.array([100.0, 110.0])
runner = CliRunner()


@pytest.fixture(scope="module")
def cstr_system():
    return get_system("cstr")


@pytest.fixture(scope="module")
def made(tmp_path_factory, cstr_system):
    """A new mpc-rl tuner of the CSTR (made once, copied by each test)."""
    where = tmp_path_factory.mktemp("made")
    (where / "config.toml").write_text(CONFIG)
    Tuner("cstr", "mpc-rl", where / "tuner", config=where / "config.toml", start_mode="random")
    return where / "tuner"


@pytest.fixture
def tuner_dir(made, tmp_path):
    shutil.copytree(made, tmp_path / "tuner")
    return tmp_path / "tuner"


@pytest.fixture(scope="module")
def server(cstr_system):
    p = SimPlant(cstr_system, cstr_system.x_ref, PERIOD, lockstep=True)
    yield p
    p.close()


@pytest.fixture
def plant(server):
    """The simulated plant, reset: no fault, no write recorded."""
    server.reset()
    return server


def _nodes(tmp_path, **extra):
    path = tmp_path / "nodes.toml"
    path.write_text(node_map(**{"timeout": 1.0, **extra}))
    return path


def _inputs_in_bounds(plant, system):
    for j, name in enumerate(system.input_names):
        u = plant.input_writes(name)
        assert np.all((u >= system.u_lb[j]) & (u <= system.u_ub[j])), (name, u.min(), u.max())
    return plant.input_writes("qs").size


def _last_input(plant):
    return np.array([plant.input_writes("qs")[-1], plant.input_writes("qc")[-1]])


def test_three_trials_are_asked_run_and_told(plant, tmp_path, cstr_system):
    (tmp_path / "config.toml").write_text(CONFIG)
    out = tmp_path / "t"
    args = ["connect", str(out), "--url", plant.url, "--nodes", str(_nodes(tmp_path))]
    args += ["--period", str(PERIOD), "--trials", "3", "--system", "cstr", "--learner", "mpc-rl"]
    res = runner.invoke(app, [*args, "--config", str(tmp_path / "config.toml")])
    assert res.exit_code == 0, res.output
    assert res.output.count("told: plant cost") == 3 and "p99 (" in res.output
    episodes = pd.read_parquet(out / "episodes.parquet")
    assert list(episodes.episode) == [0, 1, 2]
    assert Tuner.load(out).settings.start_mode == "random"  # connect's default for new tuners
    n = _inputs_in_bounds(plant, cstr_system)
    assert n == 3 * 8 + 1  # a write per period, and the safe input at the end
    written = np.c_[plant.input_writes("qs"), plant.input_writes("qc")]
    assert np.any((written == cstr_system.u_lb) | (written == cstr_system.u_ub))  # clipped
    assert np.array_equal(_last_input(plant), SAFE)
    beats = plant.input_writes("Heartbeat")
    assert np.all(np.diff(beats) == 1) and len(beats) == 3 * 8  # none with the safe input
    log = pd.read_csv(out / "trials" / "1" / "log.csv")
    assert len(log) == 9 and log[["qs", "qc"]].iloc[-1].isna().all()
    assert log["T"].between(400, 480).all()  # Kelvin: the node's Celsius converted back
    # the logged inputs are those written, in the plant's units the same here
    assert np.allclose(log["qs"].iloc[:-1], plant.input_writes("qs")[8:16])


def _repaired(plant):
    plant.fail_sensor(False)
    plant.wait_published(2)  # a good value published


def _fault_run(plant, tuner_dir, tmp_path, fault, requests=3):
    """Run one trial with ``fault`` injected after ``requests`` writes; the outcome."""
    nodes = _nodes(tmp_path, reconnect_timeout=10.0)
    thread = plant.after_writes(requests, fault)
    outcome = run_plant(Tuner.load(tuner_dir), plant.url, nodes, PERIOD)[-1]
    thread.join(5)
    return outcome, nodes


@pytest.mark.parametrize(
    ("kind", "inject", "clear", "says"),
    [
        ("stale", lambda p: p.freeze(), lambda p: p.freeze(False), "is stale"),
        ("quality", lambda p: p.fail_sensor(), lambda p: _repaired(p), "BadSensorFailure"),
        ("enable", lambda p: p.set_enable(False), lambda p: p.set_enable(True), "withdrew"),
        ("refused", lambda p: p.refuse_writes(), lambda p: p.refuse_writes(False), "refused"),
        ("connection", lambda p: p.outage(1.0), lambda p: None, "failed"),
    ],
)
def test_a_fault_aborts_the_trial_keeps_its_log_and_the_next_connect_runs_it(
    plant, tuner_dir, tmp_path, cstr_system, kind, inject, clear, says
):
    outcome, nodes = _fault_run(plant, tuner_dir, tmp_path, lambda: inject(plant))
    assert outcome.status == "aborted" and says in outcome.message, outcome.message
    assert outcome.log.name == "aborted-1.csv" and outcome.log.exists()
    assert 3 <= len(pd.read_csv(outcome.log)) < 9
    assert outcome.log.with_suffix(".json").exists()
    tuner = Tuner.load(tuner_dir)  # intact, the trial pending, nothing told
    assert tuner.episodes == 0 and tuner.status()["pending"] == outcome.trial
    if kind == "refused":
        assert "writing the safe input failed too" in outcome.message
    else:
        assert "the safe input is written" in outcome.message
        assert np.array_equal(_last_input(plant), SAFE)
    _inputs_in_bounds(plant, cstr_system)
    clear(plant)
    again = run_plant(tuner, plant.url, nodes, PERIOD)
    assert [(o.trial, o.status) for o in again] == [(outcome.trial, "told")]
    assert Tuner.load(tuner_dir).episodes == 1
    _inputs_in_bounds(plant, cstr_system)


def test_ctrl_c_writes_the_safe_input_and_exits_130(plant, tuner_dir, tmp_path, cstr_system):
    args = ["connect", str(tuner_dir), "--url", plant.url, "--nodes", str(_nodes(tmp_path))]
    for _ in range(3):  # the simulated Ctrl-C (interrupt_main) can reach a trial's last period
        tid = Tuner.load(tuner_dir).ask().id
        plant.interrupt_after(4)
        res = runner.invoke(app, [*args, "--period", str(PERIOD), "--trials", "1"])
        if res.exit_code != 0:
            break
    assert res.exit_code == 130, res.output
    assert "interrupted (SIGINT): the safe input is written;" in res.output
    assert f"trial {tid}, in progress, is not told" in " ".join(res.output.split())
    assert np.array_equal(_last_input(plant), SAFE)
    _inputs_in_bounds(plant, cstr_system)
    assert (tuner_dir / "trials" / str(tid) / "aborted-1.csv").exists()
    assert Tuner.load(tuner_dir).status()["pending"] == tid


def test_sigterm_writes_the_safe_input_first_and_exits_143(plant, tuner_dir, tmp_path, cstr_system):
    """SIGTERM (a service manager, ``kill``) during a trial stops it as Ctrl-C does: the safe
    input written, the log so far kept, the trial pending; exit code 143."""
    import signal

    args = ["connect", str(tuner_dir), "--url", plant.url, "--nodes", str(_nodes(tmp_path))]
    for _ in range(3):  # the simulated signal can reach a trial's last period
        tid = Tuner.load(tuner_dir).ask().id
        plant.interrupt_after(4, signal.SIGTERM)
        res = runner.invoke(app, [*args, "--period", str(PERIOD), "--trials", "1"])
        if res.exit_code != 0:
            break
    assert res.exit_code == 143, res.output
    assert "interrupted (SIGTERM): the safe input is written;" in res.output
    assert np.array_equal(_last_input(plant), SAFE)
    note = tuner_dir / "trials" / str(tid) / "aborted-1.json"
    assert "SIGTERM" in note.read_text()
    assert Tuner.load(tuner_dir).status()["pending"] == tid


def test_ctrl_c_between_trials_says_that_no_trial_was_in_progress(tuner_dir, tmp_path):
    """What a Ctrl-C's message says of the trials: the one in progress is not told; between
    trials none was in progress, and the told ones are named."""
    from mpcmobo.connect.session import _Session

    tuner = Tuner.load(tuner_dir)
    nodes = load_nodes(_nodes(tmp_path), tuner.system)
    session = _Session(tuner, "opc.tcp://127.0.0.1:4840", nodes, PERIOD, True, print)
    assert session.trials_said() == "no trial was in progress"
    session.told, session.in_progress = [4, 5], 6
    assert session.trials_said().startswith("trial 6, in progress, is not told")
    session.in_progress = None
    assert session.trials_said() == "no trial was in progress (told: 4, 5)"


def test_an_unreachable_server_bad_nodes_and_a_cycled_start_exit_2(plant, tuner_dir, tmp_path):
    res = runner.invoke(app, ["connect", "--help"], terminal_width=200)
    assert res.exit_code == 0 and "opc.tcp://HOST:PORT" in res.output
    nodes = _nodes(tmp_path)
    ckpt = sorted((tuner_dir / "jobs").rglob("*"))
    stamp = {p: p.stat().st_mtime_ns for p in ckpt if p.is_file()}
    base = ["connect", str(tuner_dir), "--period", str(PERIOD)]
    res = runner.invoke(
        app, [*base, "--url", f"opc.tcp://127.0.0.1:{free_port()}", "--nodes", str(nodes)]
    )
    assert res.exit_code == 2 and "cannot connect to the OPC UA server" in res.output
    bad = tmp_path / "bad.toml"
    bad.write_text(node_map().replace("CSTR.qc", "CSTR.nosuch"))
    res = runner.invoke(app, [*base, "--url", plant.url, "--nodes", str(bad)])
    assert res.exit_code == 2 and "qc (ns=2;s=CSTR.nosuch) cannot be read" in res.output
    plant.set_enable(False)
    res = runner.invoke(app, [*base, "--url", plant.url, "--nodes", str(nodes)])
    assert res.exit_code == 2 and "enable node ns=2;s=CSTR.Enable is off" in res.output
    assert plant.writes == []
    celsius = tmp_path / "celsius.toml"  # T's node holds Celsius: the map lost its offset
    celsius.write_text(node_map().replace(f", offset = {-KELVIN}", ""))
    plant.set_enable(True)
    for dry in ([], ["--dry-run"]):
        res = runner.invoke(app, [*base, "--url", plant.url, "--nodes", str(celsius), *dry])
        said = " ".join(res.output.split())
        assert res.exit_code == 2, said
        assert "the plant's reading is not a state of the system (T = " in said
        assert "check the node map's scale and offset" in said and "nothing is written" in said
    assert plant.writes == []
    boolean = tmp_path / "boolean.toml"  # an input on a Boolean node (the enable's)
    boolean.write_text(node_map().replace('qc = "ns=2;s=CSTR.qc"', 'qc = "ns=2;s=CSTR.Enable"'))
    res = runner.invoke(app, [*base, "--url", plant.url, "--nodes", str(boolean), "--dry-run"])
    said = " ".join(res.output.split())
    assert res.exit_code == 2 and "input qc (ns=2;s=CSTR.Enable) is a Boolean node" in said, said
    assert plant.writes == []
    plant.set_enable(False)
    assert {p: p.stat().st_mtime_ns for p in stamp} == stamp  # the checkpoint untouched
    (tmp_path / "cycle.toml").write_text('start_mode = "cycle"\n' + CONFIG)
    plant.set_enable(True)
    res = runner.invoke(
        app,
        ["connect", str(tmp_path / "c"), "--url", plant.url, "--nodes", str(nodes)]
        + ["--period", str(PERIOD), "--system", "cstr", "--config", str(tmp_path / "cycle.toml")],
    )
    assert res.exit_code == 2 and "bring the plant to the trial's x0" in res.output
    assert plant.writes == []


def test_a_dry_run_writes_nothing_and_tells_nothing(plant, tuner_dir, tmp_path, cstr_system):
    out = run_plant(Tuner.load(tuner_dir), plant.url, _nodes(tmp_path), PERIOD, dry_run=True)
    assert [o.status for o in out] == ["dry-run"]
    assert plant.writes == [] and Tuner.load(tuner_dir).episodes == 0
    log = pd.read_csv(out[0].log)
    u = log[["qs", "qc"]].to_numpy()[:-1]
    assert np.all((u >= cstr_system.u_lb) & (u <= cstr_system.u_ub)) and len(log) == 9


def test_credentials_come_from_the_environment_and_are_never_recorded(
    cstr_system, tuner_dir, tmp_path, monkeypatch
):
    secret = "s3cret-Pa55word"
    plant = SimPlant(cstr_system, cstr_system.x_ref, PERIOD, password=secret, lockstep=True)
    try:
        nodes = _nodes(tmp_path, password_env=True)
        monkeypatch.setenv("MPCMOBO_OPCUA_PASSWORD", "wrong")
        with pytest.raises(ConnectError, match="cannot connect") as err:
            run_plant(Tuner.load(tuner_dir), plant.url, nodes, PERIOD)
        assert "wrong" not in str(err.value)
        monkeypatch.setenv("MPCMOBO_OPCUA_PASSWORD", secret)
        out = run_plant(Tuner.load(tuner_dir), plant.url, nodes, PERIOD)
        assert [o.status for o in out] == ["told"]
        url = plant.url.replace("opc.tcp://", f"opc.tcp://operator:{secret}@")
        monkeypatch.delenv("MPCMOBO_OPCUA_PASSWORD")
        res = runner.invoke(
            app,
            [
                "connect",
                str(tuner_dir),
                "--url",
                url,
                "--nodes",
                str(nodes),
                "--period",
                str(PERIOD),
            ],
        )
        assert res.exit_code == 0, res.output
        assert secret not in res.output
    finally:
        plant.close()
    for path in tuner_dir.rglob("*"):
        if path.is_file():
            assert secret.encode() not in path.read_bytes(), path


def test_a_certificate_signs_and_encrypts_the_channel(
    cstr_system, tuner_dir, tmp_path, monkeypatch
):
    """Basic256Sha256 with SignAndEncrypt, the certificate's files from the environment; a
    client without them finds no endpoint."""
    import asyncio

    from opcua_plant import make_certificate

    plant = SimPlant(cstr_system, cstr_system.x_ref, PERIOD, certificates=tmp_path, lockstep=True)
    try:
        nodes = _nodes(tmp_path)
        with pytest.raises(ConnectError, match="No matching endpoints"):
            run_plant(Tuner.load(tuner_dir), plant.url, nodes, PERIOD)
        key, cert = tmp_path / "client-key.pem", tmp_path / "client-cert.der"
        asyncio.run(make_certificate(key, cert, "urn:example.org:FreeOpcUa:opcua-asyncio"))
        monkeypatch.setenv("MPCMOBO_OPCUA_CERTIFICATE", str(cert))
        monkeypatch.setenv("MPCMOBO_OPCUA_PRIVATE_KEY", str(key))
        monkeypatch.setenv("MPCMOBO_OPCUA_POLICY", "Basic256Sha256")
        out = run_plant(Tuner.load(tuner_dir), plant.url, nodes, PERIOD)
        assert [o.status for o in out] == ["told"]
        assert plant.input_writes("qs").size == 8 + 1
    finally:
        plant.close()


def test_a_trial_with_the_controllers_fallback_inputs_is_told(plant, tuner_dir, tmp_path):
    """Periods whose solve misses its budget write the previous plan's input (marked in the
    log's ``fallback`` column); the tuner's input check takes those steps as the controller's
    fallback, so the trial is told, not quarantined."""
    nodes = _nodes(tmp_path, solve_budget=0.001)  # a solve cannot finish within 0.15 ms
    outcome = run_plant(Tuner.load(tuner_dir), plant.url, nodes, PERIOD)[-1]
    assert outcome.status == "told" and outcome.fallbacks > 0, outcome.message
    log = pd.read_csv(outcome.log)
    assert log["fallback"].iloc[:-1].sum() == outcome.fallbacks
    assert Tuner.load(tuner_dir).status()["quarantined"] == []


def test_a_password_in_the_url_without_a_security_policy_is_warned_of(plant, tuner_dir, tmp_path):
    """The password of ``opc.tcp://user:password@host`` travels unencrypted without a security
    policy, as the node map's does: ``connect`` warns, and never prints the password."""
    url = plant.url.replace("opc.tcp://", "opc.tcp://operator:s3cret@")
    args = ["connect", str(tuner_dir), "--url", url, "--nodes", str(_nodes(tmp_path))]
    res = runner.invoke(app, [*args, "--period", str(PERIOD), "--dry-run"])
    assert "warning: no security policy: the password goes to the server unencrypted" in res.output
    assert "s3cret" not in res.output


def test_periods_whose_input_came_late_are_warned_of(plant, tuner_dir, tmp_path):
    """A period shorter than the read, the solve and the write together: the trial is told,
    and ``connect`` warns that inputs were written more than a period after their reads."""
    said: list[str] = []
    outcome = run_plant(
        Tuner.load(tuner_dir), plant.url, _nodes(tmp_path), 0.0005, echo=said.append
    )
    assert outcome[-1].status == "told", outcome[-1].message
    assert any(line.startswith("warning: in ") and "more than a period" in line for line in said)
