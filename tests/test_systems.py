"""The CSTR of the paper against an independent hand-written RK4, the stage cost, the registry."""

import dataclasses
import math
import pickle

import numpy as np
import pytest
from cstr_reference import hand_rk4, paper_rhs

from mpcmobo.mpc import ParametricMPC
from mpcmobo.systems import SearchSpace, System, get_system, register_system


def test_plant_matches_hand_written_rk4(cstr, rng):
    for _ in range(20):
        x = rng.uniform([90, 0.0, 400], [110, 0.35, 480])
        u = rng.uniform([55, 55], [140, 140])
        np.testing.assert_allclose(cstr.plant_step(x, u), hand_rk4(x, u), rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(
            cstr.model_step(x, u, "imperfect"),
            hand_rk4(x, u, mult=(1.1, 1.2, 1.15, 0.9, 1.2)),
            rtol=1e-12,
            atol=1e-12,
        )


def test_reference_is_not_an_equilibrium_but_the_noted_point_is(cstr):
    # NOTES.md: with V=105, q_s=100, q_c=110 the equilibrium is C_a=0.1181, T=434.07
    d = paper_rhs(np.array([105, 0.12, 433.0]), np.array([100, 110.0]))
    assert d[1] == pytest.approx(0.032, abs=2e-3) and d[2] == pytest.approx(-4.55, abs=0.05)
    x = np.array([105, 0.1181, 434.07])
    for _ in range(100):
        x = cstr.plant_step(x, np.array([100, 110.0]))
    assert abs(x[0] - 105) < 1e-9 and abs(x[1] - 0.1181) < 2e-4 and abs(x[2] - 434.07) < 0.05


def test_stage_cost(cstr):
    xr, ur = cstr.x_ref, cstr.u_ref
    assert cstr.stage_cost(xr, ur) == 0.0
    x = xr + np.array([1.0, 0.01, -2.0])
    u = ur + np.array([3.0, -1.0])
    expected = 10 * 1 + 5000 * 1e-4 + 10 * 4 + 10 * 9 + 10 * 1
    assert cstr.stage_cost(x, u) == pytest.approx(expected)
    # a violated state bound costs Gamma = 1e5 per unit of violation (section 5)
    xv = np.array([105.0, 0.36, 433.0])
    base = 5000 * (0.36 - 0.12) ** 2
    assert cstr.stage_cost(xv, ur) == pytest.approx(base + 1e5 * 0.01)
    assert cstr.constraint_violation(xv) == pytest.approx(0.01)


def test_bad_inputs_raise_clear_errors(cstr):
    with pytest.raises(ValueError, match="unknown system 'nope'"):
        get_system("nope")
    with pytest.raises(ValueError, match="shape"):
        cstr.plant_step(np.zeros(2), np.zeros(2))
    with pytest.raises(ValueError, match="NaN"):
        cstr.stage_cost(np.array([np.nan, 0.1, 430]), np.zeros(2))
    with pytest.raises(ValueError, match="unknown model"):
        ParametricMPC(cstr, model="wrong")


def test_parameterization_and_search_space(cstr):
    P = cstr.parameterization
    assert len(P.names) == 14
    assert P.names[:4] == ("theta_c", "T_V", "T_Ca", "T_T")
    np.testing.assert_array_equal(P.theta0[P.blocks["Q"]], [10, 5000, 10])
    np.testing.assert_array_equal(P.theta0[P.blocks["R"]], [10, 10])
    np.testing.assert_array_equal(P.theta0[P.blocks["G"]], 0)
    space = cstr.search_space
    assert space.dim == 13 and space.fixed[0]
    # weights may move by e^4 either way (NOTES.md)
    assert space.upper[P.blocks["Q"]][1] == pytest.approx(5000 * math.e**4)
    z = space.to_unit(P.theta0)
    np.testing.assert_allclose(space.from_unit(z, P.theta0), P.theta0, atol=1e-9)
    assert space.contains(P.theta0)


def test_search_space_roundtrip_and_errors():
    s = SearchSpace(["a", "b", "c"], [1, -1, 0], [100, 1, 0], log=[True, False, False])
    assert s.dim == 2  # zero-width interval is fixed
    z = np.array([0.5, 0.25])
    th = s.from_unit(z, base=np.array([1.0, 0.0, 0.0]))
    assert th[0] == pytest.approx(10.0) and th[1] == pytest.approx(-0.5)
    np.testing.assert_allclose(s.to_unit(th), z)
    with pytest.raises(ValueError, match="positive"):
        SearchSpace(["a"], [0], [1], log=[True])
    with pytest.raises(ValueError, match="lower > upper"):
        SearchSpace(["a"], [2], [1])


def test_learnable_model_parameters_and_second_system():
    s = get_system("cstr").with_spec(learn_model=("k0", "k3"), learn_backoff=True)
    P = s.parameterization
    assert P.names[-8:-6] == ("model_k0", "model_k3")
    assert P.theta0[P.blocks["model"]].tolist() == [1.2, 1.2]
    lq = get_system("lq")
    assert lq.nx == 2 and lq.parameterization.n_theta == 1 + 2 + 3 + 2 + 1


def test_derived_parts_are_built_once_and_follow_copies(cstr):
    assert cstr.parameterization is cstr.parameterization
    assert cstr.search_space is cstr.parameterization.space
    with pytest.raises(dataclasses.FrozenInstanceError):
        cstr.mpc_spec = cstr.mpc_spec  # a change would leave the derived parts stale
    s = cstr.with_spec(learn_backoff=True)
    assert s.parameterization.n_theta == cstr.parameterization.n_theta + 2 * cstr.nx
    assert cstr.parameterization.n_theta == 14
    t = pickle.loads(pickle.dumps(s))
    assert t.parameterization.names == s.parameterization.names
    x, u = cstr.x_ref, cstr.u_ref
    np.testing.assert_array_equal(t.plant_step(x, u), cstr.plant_step(x, u))
    # each system owns its arrays (none aliases the module constants of cstr.py)
    assert not np.shares_memory(s.true_params, cstr.true_params)
    # the one RK4 function: the plant with p = true_params, the model with p = models[...]
    F = cstr.discrete_step
    np.testing.assert_array_equal(F(x, u, cstr.true_params).full().ravel(), cstr.plant_step(x, u))
    np.testing.assert_array_equal(
        F(x, u, cstr.models["imperfect"]).full().ravel(), cstr.model_step(x, u, "imperfect")
    )


def test_mpc_predicts_with_the_systems_model(cstr, cstr_mpc):
    x = np.array([100.0, 0.2, 420.0])
    sol = cstr_mpc.solve(x, cstr_mpc.theta0, sensitivities=False)
    pred = cstr.model_step(sol.plan_x[0], sol.plan_u[0], "imperfect")
    np.testing.assert_allclose(sol.plan_x[1], pred, rtol=1e-7, atol=1e-9)


def test_register_user_system():
    def factory():
        import casadi as ca

        return System(
            name="tank",
            state_names=["h"],
            input_names=["q"],
            dynamics=lambda x, u, p: ca.vertcat(-p[0] * x[0] + u[0]),
            param_names=["a"],
            true_params=[1.0],
            models={"imperfect": [1.5]},
            dt=0.1,
            x_ref=[1.0],
            u_ref=[1.0],
            x_lb=[0.0],
            x_ub=[2.0],
            u_lb=[0.0],
            u_ub=[3.0],
            Q=[1.0],
            R=[0.1],
            Gamma=[100.0],
            x0_lb=[0.2],
            x0_ub=[1.8],
        )

    register_system("tank-test", factory, overwrite=True)
    tank = get_system("tank-test")
    mpc = ParametricMPC(tank)
    sol = mpc.solve(np.array([0.5]), mpc.theta0)
    assert sol.success and sol.action[0] > 1.0  # pushes the level up towards 1
    with pytest.raises(ValueError, match="already registered"):
        register_system("tank-test", factory)
    # a factory without keyword arguments takes the study's MPC settings as a file's does
    tank = get_system("tank-test", identify=("a",), horizon=7)
    assert tank.mpc_spec.horizon == 7 and "model_a" in tank.parameterization.names


def test_dtheta_dz_matches_finite_differences(cstr):
    space, th0 = cstr.search_space, cstr.parameterization.theta0
    z = space.to_unit(th0)
    J = space.dtheta_dz(th0)
    for j in range(space.dim):
        h = 1e-6
        zp, zm = z.copy(), z.copy()
        zp[j] += h
        zm[j] -= h
        fd = (space.from_unit(zp, th0) - space.from_unit(zm, th0))[space.free][j] / (2 * h)
        assert fd == pytest.approx(J[j], rel=1e-5)
