"""The parts of mpcmobo connect without a server: the node map (checked against the system,
credentials from the environment and never shown) and the controller on a deadline (a solve
that overruns the period gives the last plan's input for that period)."""

from __future__ import annotations

import time
from types import SimpleNamespace

import numpy as np
import pytest

from mpcmobo.connect.client import public_url
from mpcmobo.connect.nodes import ConnectError, load_nodes
from mpcmobo.connect.runner import Controller
from mpcmobo.experiment.tuner import Trial
from mpcmobo.systems import get_system

NODES = """\
[states]
V = "ns=2;s=V"
Ca = "ns=2;s=Ca"
T = { node = "ns=2;s=T", scale = 1.8, offset = -459.67 }
[inputs]
qs = "ns=2;s=qs"
qc = "ns=2;s=qc"
[safe_input]
qs = 100.0
qc = 110.0
[security]
user = "operator"
password = "from-the-file"
"""


@pytest.fixture(scope="module")
def cstr():
    return get_system("cstr")


def test_the_node_map_is_checked_and_its_secrets_never_shown(cstr, tmp_path, monkeypatch):
    path = tmp_path / "nodes.toml"
    path.write_text(NODES)
    nodes = load_nodes(path, cstr)
    assert nodes.states["T"].scale == 1.8 and nodes.states["V"].offset == 0.0
    assert nodes.security.password.get_secret_value() == "from-the-file"
    monkeypatch.setenv("MPCMOBO_OPCUA_PASSWORD", "from-the-env")
    nodes = load_nodes(path, cstr)
    assert nodes.security.password.get_secret_value() == "from-the-env"  # the environment wins
    shown = repr(nodes) + str(nodes.model_dump()) + nodes.model_dump_json()
    assert "from-the-env" not in shown and "from-the-file" not in shown
    monkeypatch.delenv("MPCMOBO_OPCUA_PASSWORD")
    for text, says in [
        (
            NODES.replace("scale = 1.8", "scale = 0"),
            "states.T.scale: Value error, scale cannot be 0",
        ),
        (NODES.replace('qc = "ns=2;s=qc"', 'qx = "ns=2;s=qc"'), "[inputs] has no 'qc'"),
        (NODES.replace("qc = 110.0", "qc = 110.0\nqz = 1.0"), "[safe_input] names 'qz'"),
        (NODES.replace("qc = 110.0", "qc = 10.0"), "safe_input qc = 10 is outside its bounds"),
        (
            "stale_periods = 0\n" + NODES,
            "stale_periods: Input should be greater than or equal to 1",
        ),
        (NODES.replace('password = "from-the-file"', "password = 12"), "security.password"),
        (
            "stale_period = 3\n" + NODES,
            "stale_period: unknown key; allowed keys here: states, inputs, safe_input, enable",
        ),
        (
            NODES.replace("scale = 1.8", "sclae = 1.8"),
            "states.T.sclae: unknown key; allowed keys here: node, scale, offset",
        ),
        (
            NODES.replace('password = "from-the-file"', 'pasword = "from-the-file"'),
            "security.pasword: unknown key; allowed keys here: user, password, certificate",
        ),
        ("[states\n", "cannot be read"),
        (NODES + 'policy = "Basic256Sha256"\n', "policy Basic256Sha256 needs a certificate"),
    ]:
        path.write_text(text)
        with pytest.raises(ConnectError) as err:
            load_nodes(path, cstr)
        assert says in str(err.value), str(err.value)
        msg = str(err.value).replace(str(path), "NODES")  # the temporary path may hold "12"
        assert "from-the" not in msg and "12" not in msg.split(":")[-1], msg
    with pytest.raises(ConnectError, match="does not exist"):
        load_nodes(tmp_path / "none.toml", cstr)
    assert public_url("opc.tcp://op:pw@host:4840/p") == "opc.tcp://host:4840/p"


class _SlowMPC:
    """A controller whose plan at period k is k + 10 * stage, and whose solve takes
    ``delays[call]`` seconds."""

    def __init__(self, delays):
        self.delays, self.calls = list(delays), 0

    def solve(self, x, theta, sensitivities=False):
        time.sleep(self.delays[self.calls])
        self.calls += 1
        plan = np.array([[x[0] + 10.0 * i] * 2 for i in range(5)])
        return SimpleNamespace(action=plan[0], plan_u=plan, fallback=False)

    def fallback_action(self):
        return np.array([100.0, 110.0])


def test_a_solve_that_overruns_gives_the_last_plans_input(cstr):
    import asyncio

    mpc = _SlowMPC([0.0, 0.0, 0.3, 0.0])
    trial = Trial(0, np.zeros(1), np.zeros((6, 2)), 6, np.zeros(3), ("a",), mpc)  # type: ignore[arg-type]
    ctrl = Controller(trial, cstr, 0.1)

    async def run():
        ctrl.prime(np.array([60.0]))  # the plan of period 0: 60, 70, 80, ...
        out = [ctrl.action(np.array([61.0]), 0, 0.1)]  # on time: its plan replaces it
        out.append(ctrl.action(np.array([62.0]), 1, 0.05))  # overruns
        out.append(ctrl.action(np.array([63.0]), 2, 0.05))  # the worker is still busy
        await asyncio.sleep(0.35)
        out.append(ctrl.action(np.array([64.0]), 3, 0.1))  # free again, on time
        return out

    (u0, f0, t0), (u1, f1, _), (u2, f2, _), (u3, f3, _) = asyncio.run(run())
    ctrl.close()
    assert not f0 and np.allclose(u0, 61.0) and t0 >= 0
    assert f1 and np.allclose(u1, 71.0)  # period 1 of the plan made at period 0
    assert f2 and np.allclose(u2, 81.0)  # period 2 of that plan
    assert not f3 and np.allclose(u3, 64.0)
    assert mpc.calls == 4


def test_an_error_inside_a_trial_aborts_it_with_the_log_so_far(cstr):
    """Any exception in a period (here the MPC's) is an aborted trial, its log kept."""
    import asyncio

    from mpcmobo.connect.client import Reading
    from mpcmobo.connect.nodes import NodeMap
    from mpcmobo.connect.runner import Aborted, run_trial

    class _Client:
        system = cstr

        async def read(self):
            return Reading(np.array(cstr.x_ref), (None, None, None), True)

        async def write(self, u):
            pass

    mpc = _SlowMPC([0.0] * 3)
    mpc.delays.append("not a number")  # the fourth solve raises a TypeError
    trial = Trial(0, np.zeros(1), np.zeros((6, 2)), 6, np.zeros(3), ("a",), mpc)  # type: ignore[arg-type]
    nodes = NodeMap.model_validate(
        {"states": {}, "inputs": {}, "safe_input": {}, "solve_budget": 0.5}
    )
    with pytest.raises(Aborted, match="TypeError") as err:
        asyncio.run(run_trial(_Client(), trial, nodes, 0.02, asyncio.run(_Client().read())))
    assert err.value.kind == "error" and len(err.value.log.rows) == 2
