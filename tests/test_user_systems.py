"""Any plant, any model: validation of a system at build, discrete models, path
constraints, full weights, the plant as a gymnasium environment, systems found by factory path
or plug-in, J* absent. The CLI acceptance test is in tests/test_user_systems_cli.py."""

from __future__ import annotations

import dataclasses
import json
import math
import sys

import casadi as ca
import gymnasium
import numpy as np
import pytest
from cstr_reference import fd_sensitivities
from gymnasium.utils.env_checker import check_env
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from user_system_source import SYSTEM, write_user_files

import mpcmobo  # noqa: F401 - registers mpcmobo/CSTR-v0
from mpcmobo.experiment import storage
from mpcmobo.experiment.settings import SettingsError, load_settings
from mpcmobo.experiment.study import run_study
from mpcmobo.mpc import ParametricMPC, rollout
from mpcmobo.systems import (
    MPCSpec,
    System,
    SystemDefinitionError,
    SystemSpecError,
    get_system,
    make_plant,
)
from mpcmobo.systems.plant import SystemPlant
from mpcmobo.systems.registry import describe_systems


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    return write_user_files(tmp_path_factory.mktemp("user"))


def lq_fields(**changes) -> dict:
    """The keyword arguments of the built-in lq system, with ``changes``."""
    s = get_system("lq")
    d = {f.name: getattr(s, f.name) for f in dataclasses.fields(s) if f.init}
    d.update(changes)
    return d


# ---------------------------------------------------------------------- validation
@pytest.mark.parametrize(
    "changes, match",
    [
        (
            {"dynamics": lambda x, u, p: x[0] + u[0]},
            r"lq.dynamics .* returns shape \(1, 1\), "
            r"expected \(2 states",
        ),
        ({"dynamics": lambda x, u, p: ca.vertcat(x, u)}, r"lq.dynamics .*shape \(3, 1\)"),
        (
            {"dynamics": lambda x, u, p: x[5]},
            r"lq.dynamics .*cannot be evaluated on CasADi symbols: RuntimeError: [^\n]*out of bounds",
        ),
        ({"x0_lb": [-20.0, -1.0]}, r"lq.x0_lb/x0_ub: .*'p' is not inside the state bounds"),
        ({"x_lb": [11.0, -10.0]}, r"lq.x_lb exceeds lq.x_ub for 'p'"),
        ({"u_lb": [6.0]}, r"lq.u_lb exceeds lq.u_ub for 'f'"),
        ({"Q": [1.0, 0.0]}, r"lq.Q must be positive .* for 'v'"),
        ({"R": [-1.0]}, r"lq.R must be positive"),
        ({"Gamma": [1.0, -1.0]}, r"lq.Gamma must be >= 0"),
        ({"models": {"wrong": [1, 1, 1]}}, r"lq.models needs 'imperfect'"),
        ({"models": {"imperfect": [1, 1]}}, r"lq.models\['imperfect'\] has 2 entries, expected 3"),
        ({"x_ref": [0.0]}, r"lq.x_ref has 1 entries, expected 2"),
        ({"dt": 0.0}, r"lq.dt must be a positive number"),
        ({"state_names": ("p", "p")}, r"lq.state_names has a repeated name"),
        ({"episode_steps": 0}, r"lq.episode_steps must be an integer >= 1"),
        ({"Gamma_h": [1.0]}, r"lq.Gamma_h is given without path_constraints"),
        (
            {"path_constraints": lambda x, u: ca.vertcat(x[0], x[1]), "constraint_names": ["a"]},
            r"lq.path_constraints returns shape \(2, 1\), expected \(1 constraints",
        ),
    ],
)
def test_a_bad_system_is_refused_naming_the_field(changes, match):
    with pytest.raises(SystemDefinitionError, match=match):
        System(**lq_fields(**changes))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    lo=st.lists(st.floats(-50, 50), min_size=2, max_size=2),
    width=st.lists(st.floats(-5, 5), min_size=2, max_size=2),
)
def test_any_bound_box_is_accepted_only_if_ordered_and_containing_the_starts(lo, width):
    lb, ub = np.array(lo), np.array(lo) + np.array(width)
    s = get_system("lq")
    ok = np.all(lb <= ub) and np.all(lb <= s.x0_lb) and np.all(ub >= s.x0_ub)
    if ok:
        System(**lq_fields(x_lb=lb, x_ub=ub))
    else:
        with pytest.raises(SystemDefinitionError, match=r"lq\.x(0)?_lb"):
            System(**lq_fields(x_lb=lb, x_ub=ub))


# ---------------------------------------------------------------------- discrete models
def di_system(files, **kw) -> System:
    from mpcmobo.systems.registry import load_object

    return load_object(f"{files}/usersys.py:make_system")(**kw)


def test_a_discrete_map_is_used_as_it_is_by_plant_model_and_mpc(files):
    s = di_system(files)
    x, u = np.array([0.3, -0.2]), np.array([0.7])
    dt = 0.2
    exact = np.array([x[0] + dt * x[1] + 0.5 * dt**2 * u[0], x[1] + dt * u[0]])
    np.testing.assert_array_equal(s.plant_step(x, u), exact)  # no RK4 around the map
    np.testing.assert_allclose(
        s.model_step(x, u, "imperfect"),
        [x[0] + dt * x[1] + 0.5 * dt**2 * 0.6 * u[0], x[1] + dt * 0.6 * u[0]],
        rtol=0,
        atol=1e-15,
    )
    mpc = ParametricMPC(s)
    sol = mpc.solve(x, mpc.theta0, sensitivities=False)
    np.testing.assert_allclose(sol.plan_x[1], s.model_step(x, sol.plan_u[0]), atol=1e-8)


# ---------------------------------------------------------------------- path constraints
def test_path_constraint_holds_in_the_plan_and_its_violation_is_costed(files):
    s = di_system(files)
    assert s.nh == 1 and s.constraint_names == ("h0",)
    mpc = ParametricMPC(s)
    x = np.array([0.4, 1.5])  # h = 1.15 - 1.5 < 0, moving fast towards the constraint
    sol = mpc.solve(x, mpc.theta0, sensitivities=False)
    h = [s.path_values(xi, ui)[0] for xi, ui in zip(sol.plan_x[:-1], sol.plan_u)]
    assert max(h) <= 1e-5 and sol.slack < 1e-4  # held without slack
    free = ParametricMPC(di_system(files, path=False)).solve(x, sensitivities=False)
    hf = [s.path_values(xi, ui)[0] for xi, ui in zip(free.plan_x[:-1], free.plan_u)]
    assert max(hf) > 0.05  # without the constraint the plan crosses it
    xv, u = np.array([2.0, 0.0]), np.array([0.0])  # h = 0.5
    assert s.constraint_violation(xv, u) == pytest.approx(0.5)
    assert s.stage_cost(xv, u) == pytest.approx(4.0 + s.Gamma_h[0] * 0.5)


def test_sensitivities_with_path_constraints_and_full_weights_match_finite_differences(files):
    s = di_system(files).with_spec(full_weights=True)
    mpc = ParametricMPC(s)
    x = np.array([1.1, 0.6])
    rng = np.random.default_rng(3)
    theta = s.search_space.clip(mpc.theta0 * (1 + 0.2 * rng.standard_normal(mpc.n_theta)))
    sol = mpc.solve(x, theta)
    assert sol.success
    dpi, dV = fd_sensitivities(mpc, x, theta)
    np.testing.assert_allclose(sol.dpi_dtheta, dpi, rtol=1e-3, atol=1e-4)
    np.testing.assert_allclose(sol.dV_dtheta, dV, rtol=1e-3, atol=1e-4)


def test_full_weights_start_at_the_diagonal_and_stay_positive_definite(files):
    from mpcmobo.systems.parameterization import weight_matrix

    diag = di_system(files)
    full = diag.with_spec(full_weights=True)
    P = full.parameterization
    assert P.names[P.blocks["Q"]][:3] == ("LQ_pos_pos", "LQ_vel_pos", "LQ_vel_vel")
    Q0 = weight_matrix(P.theta0[P.blocks["Q"]], 2)
    np.testing.assert_allclose(Q0, np.diag(diag.Q))
    x = np.array([1.0, -0.3])
    a = ParametricMPC(diag).solve(x, sensitivities=False)
    b = ParametricMPC(full).solve(x, sensitivities=False)
    np.testing.assert_allclose(a.action, b.action, atol=1e-7)  # same MPC at theta0
    space = P.space
    for z in np.random.default_rng(0).uniform(size=(50, space.dim)):
        th = space.from_unit(z, P.theta0)
        for blk, n in (("Q", 2), ("T", 2), ("R", 1)):
            assert np.linalg.eigvalsh(weight_matrix(th[P.blocks[blk]], n)).min() > 0


# ---------------------------------------------------------------------- the plant
def test_the_cstr_plant_is_a_registered_gymnasium_environment(cstr):
    env = gymnasium.make("mpcmobo/CSTR-v0")
    check_env(env.unwrapped, skip_render_check=True)
    check_env(SystemPlant("lq"), skip_render_check=True)
    obs, _ = env.reset(seed=1, options={"x0": cstr.x_ref})
    u = cstr.u_ref + 1.0
    obs2, reward, terminated, truncated, info = env.step(u)
    np.testing.assert_array_equal(obs2, cstr.plant_step(cstr.x_ref, u))
    assert info["stage_cost"] == cstr.stage_cost(cstr.x_ref, u) == -reward
    assert info["violation"] == 0.0 and not terminated and not truncated
    assert env.spec.max_episode_steps == cstr.episode_steps


def test_rollout_through_an_environment_equals_the_systems_own_plant():
    lq = get_system("lq")
    mpc = ParametricMPC(lq)
    x0 = np.array([1.0, -0.5])
    a = rollout(lq, mpc, None, x0, 10, sensitivities=False)
    b = rollout(lq, mpc, None, x0, 10, sensitivities=False, plant=gymnasium.make("mpcmobo/LQ-v0"))
    for field in ("x", "u", "L", "violation", "V"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field))


def test_a_plant_that_terminates_shortens_the_episode():
    lq = get_system("lq")

    class Stops(SystemPlant):
        def step(self, action):
            obs, r, _, trunc, info = super().step(action)
            self.k = getattr(self, "k", 0) + 1
            return obs, r, self.k >= 4, trunc, {"stage_cost": 7.0}  # no "violation"

    rec = rollout(
        lq, ParametricMPC(lq), None, np.array([1.0, 0.0]), 10, sensitivities=False, plant=Stops(lq)
    )
    assert rec.steps == 4 and rec.x.shape == (5, 2) and rec.V.shape == (5,)
    # the stage cost comes from the plant's info; a missing violation from the model
    np.testing.assert_array_equal(rec.L, 7.0)
    np.testing.assert_array_equal(rec.violation, 0.0)


def test_plant_sizes_must_match_the_model(files):
    s = di_system(files)
    with pytest.raises(
        SystemDefinitionError,
        match=r"observation space has shape \(3,\).* 2 "
        r"states \(pos, vel\)",
    ):
        make_plant(f"{files}/userplant.py:make_env_3", s)
    with pytest.raises(
        SystemDefinitionError,
        match=r"action space has shape \(1,\), but the model .* has 2 inputs \(a, b\)",
    ):
        two_inputs = dataclasses.replace(
            s,
            input_names=("a", "b"),
            u_ref=[0, 0],
            u_lb=[-1, -1],
            u_ub=[1, 1],
            R=[1, 1],
            u_scale=None,
        )
        make_plant(f"{files}/userplant.py:make_env", two_inputs)


# ---------------------------------------------------------------------- finding systems
def test_systems_by_factory_path_module_and_plugin(files, tmp_path, monkeypatch):
    assert get_system(f"{files}/usersys.py:make_system").name == "double_integrator"
    monkeypatch.syspath_prepend(str(files))
    assert get_system("usersys:make_system").discrete_time
    with pytest.raises(SystemSpecError, match="cannot import module 'nope_mod'"):
        get_system("nope_mod:make_system")
    with pytest.raises(SystemSpecError, match="file not found"):
        get_system(f"{files}/missing.py:make_system")
    with pytest.raises(SystemSpecError, match="cannot import .*broken.py: SyntaxError"):
        get_system(f"{files}/broken.py:make_system")
    with pytest.raises(SystemSpecError, match="has no attribute 'nope'"):
        get_system(f"{files}/usersys.py:nope")
    with pytest.raises(SystemSpecError, match="returned dict, expected a mpcmobo.systems.System"):
        get_system(f"{files}/usersys.py:make_wrong_type")
    with pytest.raises(SystemDefinitionError, match=r"make_broadcast.*dynamics.*\(1, 1\)"):
        get_system(f"{files}/usersys.py:make_broadcast")
    # an installed plug-in: an entry point of the group mpcmobo.systems
    dist = tmp_path / "userplug-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: userplug\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text("[mpcmobo.systems]\ndi = usersys:make_system\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert ("di", "plug-in usersys:make_system (userplug)") in describe_systems()
    assert get_system("di").name == "double_integrator"
    s = load_settings(None, system={"name": "di", "learn_model": ["gain"]})
    assert s.system.name == "di"


def test_a_factory_file_imports_the_modules_beside_it(tmp_path, monkeypatch):
    """A factory path's file imports a module in its own folder, as a script run there would
    (the system in one file, its equations in another)."""
    folder = tmp_path / "mine"
    folder.mkdir()
    (folder / "equations_beside.py").write_text(SYSTEM)
    (folder / "entry.py").write_text(
        "import equations_beside\n\n\ndef make_system():\n"
        "    return equations_beside.make_system(path=False)\n"
    )
    monkeypatch.setattr(sys, "path", list(sys.path))  # the folder added here goes with the test
    monkeypatch.delitem(sys.modules, "equations_beside", raising=False)
    assert get_system(f"{folder}/entry.py:make_system").name == "double_integrator"
    assert sys.path[-1] == str(folder.resolve())


def test_settings_take_a_factory_path_and_store_it_absolute(files, monkeypatch):
    monkeypatch.chdir(files)
    s = load_settings(None, system={"factory": "usersys.py:make_system"}).resolved()
    assert s.system.factory == f"{files}/usersys.py:make_system"
    assert s.system.name == "double_integrator"
    assert load_settings(None, **s.to_dict()).system.factory == s.system.factory
    with pytest.raises(SettingsError, match="is a factory path; give it as system.factory"):
        load_settings(None, system={"name": "usersys.py:make_system"})


# ---------------------------------------------------------------------- J* absent
def _model_on_plant(files, plant, **settings):
    """Settings of the model without true parameters on the gymnasium plant ``plant``."""
    system = {"factory": f"{files}/usersys.py:make_model", "plant": f"{files}/userplant.py:{plant}"}
    return load_settings(None, system=system, workers=1, **settings)


def test_a_gymnasium_plant_with_a_separate_model_and_no_J_star(files, tmp_path):
    """Acceptance: a gymnasium environment that is not a mpcmobo system is the plant of a
    study; the model has no true parameters, so J* is absent and every summary says so."""
    settings = _model_on_plant(
        files,
        "make_env",
        learners=["mpc-rl", "bo"],
        episodes=3,
        evaluation={"n_starts": 2, "eval_every": 1},
    )
    out = tmp_path / "run"
    summary = run_study(settings, out)
    assert summary["J_star"] is None and "no reference model" in summary["J_star_missing"]
    assert "below J_initial" in summary["episodes_to_target"]
    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk["J_star"] is None and on_disk["J_star_missing"] == summary["J_star_missing"]
    for name in ("mpc-rl", "bo"):
        s = summary["learners"][name]
        assert s["J_star"] is None and s["complete"]
        # the fallback target: a 2% improvement over theta0
        rows = storage.read_episodes(out)
        rows = rows[(rows.learner == name) & np.isfinite(rows.J_eval_incumbent)]
        hits = rows[rows.J_eval_incumbent <= 0.98 * summary["J_initial"]]
        expected = int(hits.episode.min()) if len(hits) else None
        assert s["per_seed"]["0"]["episodes_to_2pct"] == expected
        assert math.isclose(s["improvement_over_theta0"], 1 - s["J_final"] / s["J_initial"])
    assert "perfect" not in set(storage.read_trajectories(out)["phase"])  # no J* episodes
    from mpcmobo.plots import make_figures

    assert all(p.exists() for p in make_figures(out))


def test_a_plant_that_ignores_its_start_is_refused_before_anything_is_written(files, tmp_path):
    """A gymnasium plant whose reset ignores options['x0'] (it starts at the origin): every
    comparison of thetas would be meaningless, so the study stops before it starts."""
    settings = _model_on_plant(files, "make_stubborn_env", learners=["bo"], episodes=2)
    with pytest.raises(SettingsError, match=r"did not start the plant at x0 \(asked"):
        run_study(settings, tmp_path / "run")
    assert not (tmp_path / "run").exists()


def test_an_unknown_plant_is_a_settings_error(files):
    settings = load_settings(None, system={"name": "lq", "plant": "mpcmobo/Nope-v0"})
    from mpcmobo.experiment.build import build_plant, build_system

    with pytest.raises(SettingsError, match="system.plant: plant 'mpcmobo/Nope-v0'"):
        build_plant(settings, build_system(settings))
    assert isinstance(MPCSpec(), MPCSpec)
