"""The continuous stirred tank reactor of section 5 (Table 1, eq. CSTR_model, CSTR_Wrongmodel)."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

import casadi as ca
import numpy as np

from mpcmobo.systems.base import System
from mpcmobo.systems.parameterization import MPCSpec

# Table 1 of the paper.
Q_O = 100.0  # process flow rate [l/min]
C_AO = 1.0  # feed concentration [mol/l]
T_O = 350.0  # feed temperature [K]
T_CO = 350.0  # inlet coolant temperature [K]
DELTA_H = -2e5  # heat of reaction [cal/mol]
RHO_CP = 1000.0  # [cal/(l K)]
K0 = 7.2e10  # reaction rate [1/min]
E_R = 1e4  # activation energy term E/R [K]
RHOC_CPC = 1000.0  # [cal/(l K)]
HA = 7e5  # heat transfer coefficient [cal/(min K)]

K1 = -DELTA_H * K0 / RHO_CP
K2 = RHOC_CPC / RHO_CP
K3 = HA / RHOC_CPC

# Model parameters are multipliers of the terms of eq. (CSTR_model); the imperfect model of
# eq. (CSTR_Wrongmodel) multiplies them by 1.1, 1.2, 1.15, 0.9 and 1.2.
PARAM_NAMES = ("feed", "k0", "k1", "k2", "k3")
TRUE_PARAMS = np.ones(5)
IMPERFECT_PARAMS = np.array([1.1, 1.2, 1.15, 0.9, 1.2])


def cstr_dynamics(x: ca.SX, u: ca.SX, p: ca.SX) -> ca.SX:
    """Right-hand side of eq. (CSTR_model), with multipliers ``p`` on its terms.

    x = (V [l], C_a [mol/l], T [K]), u = (q_s, q_c) [l/min]. With ``p = 1`` this is the true
    plant; with ``p = (1.1, 1.2, 1.15, 0.9, 1.2)`` it is eq. (CSTR_Wrongmodel).
    """
    return _balances(x, u, p, ca.exp(-E_R / x[2]))


def _balances(x: ca.SX, u: ca.SX, p: ca.SX, arrhenius: ca.SX) -> ca.SX:
    """The mass and energy balances of eq. (CSTR_model) with the multipliers ``p[:5]`` and
    the reaction's temperature dependence ``arrhenius``."""
    V, Ca, T = x[0], x[1], x[2]
    qs, qc = u[0], u[1]
    dV = Q_O - qs
    dCa = p[0] * Q_O / V * (C_AO - Ca) - p[1] * K0 * arrhenius * Ca
    dT = (
        Q_O / V * (T_O - T)
        + p[2] * K1 * arrhenius * Ca
        + p[3] * K2 * qc / V * (1 - ca.exp(-p[4] * K3 / qc)) * (T_CO - T)
    )
    return ca.vertcat(dV, dCa, dT)


def make_cstr(**spec_overrides: Any) -> System:
    """The CSTR benchmark: true plant, imperfect model, bounds, references and stage cost."""
    spec = MPCSpec(
        horizon=10,
        gamma=0.99,
        Gamma=np.full(3, 1e5),
        Gamma_f=np.full(3, 1e5),
    )
    spec = spec.with_overrides("CSTR", **spec_overrides)
    return System(
        name="cstr",
        description="Continuous stirred tank reactor (A -> B, exothermic), paper section 5",
        state_names=("V", "Ca", "T"),
        input_names=("qs", "qc"),
        dynamics=cstr_dynamics,
        param_names=PARAM_NAMES,
        true_params=TRUE_PARAMS,
        models={"perfect": TRUE_PARAMS, "imperfect": IMPERFECT_PARAMS},
        dt=0.05,
        x_ref=np.array([105.0, 0.12, 433.0]),
        u_ref=np.array([100.0, 110.0]),
        x_lb=np.array([90.0, 0.0, 400.0]),
        x_ub=np.array([110.0, 0.35, 480.0]),
        u_lb=np.array([55.0, 55.0]),
        u_ub=np.array([140.0, 140.0]),
        Q=np.array([10.0, 5000.0, 10.0]),
        R=np.array([10.0, 10.0]),
        Gamma=np.full(3, 1e5),
        x0_lb=np.array([95.0, 0.05, 410.0]),
        x0_ub=np.array([105.0, 0.30, 450.0]),
        episode_steps=60,
        mpc_spec=spec,
    )


# The structural variant: the plant's reaction has an activation energy ACTIVATION times the
# model's, its rate constant scaled so that at the reference (T 433 K) it reacts as the paper's
# plant does. The model and theta0 are the paper's; identification fits the five multipliers,
# which can match the plant's rate at one temperature but not its sensitivity to temperature.
ACTIVATION = 1.04
STRUCTURAL_NAMES = (*PARAM_NAMES, "activation")
STRUCTURAL_TRUE = np.array(
    [1.0, *(2 * [np.exp((ACTIVATION - 1) * E_R / 433.0)]), 1.0, 1.0, ACTIVATION]
)
STRUCTURAL_MODEL = np.array([*IMPERFECT_PARAMS, 1.0])


def structural_dynamics(x: ca.SX, u: ca.SX, p: ca.SX) -> ca.SX:
    """eq. (CSTR_model) with multipliers ``p[:5]`` and ``p[5]`` a factor on the activation
    energy E/R of the reaction."""
    return _balances(x, u, p, ca.exp(-p[5] * E_R / x[2]))


def make_cstr_structural(**spec_overrides: Any) -> System:
    """The CSTR whose plant has a structure its model lacks (an activation energy 4% above
    the model's): the paper's model, theta0, bounds and costs; identification fits the
    multipliers only."""
    base = make_cstr(**spec_overrides)
    return replace(
        base,
        name="cstr-structural",
        description="The CSTR whose plant's activation energy is 4% above its model's "
        "(structural mismatch)",
        dynamics=structural_dynamics,
        param_names=STRUCTURAL_NAMES,
        true_params=STRUCTURAL_TRUE,
        models={"perfect": STRUCTURAL_TRUE, "imperfect": STRUCTURAL_MODEL},
        identifiable=PARAM_NAMES,
    )
