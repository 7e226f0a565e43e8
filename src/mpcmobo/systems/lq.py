"""A small linear-quadratic system: the second system, and a test bed for CDPG.

``dx/dt = [[0, 1], [-p0, -p1]] x + [0, p2] u``, a damped oscillator driven by one input.
The true plant has ``p = (1, 0.5, 1)``; the imperfect model ``p = (1.3, 0.3, 0.8)``.
"""

from __future__ import annotations

from typing import Any

import casadi as ca
import numpy as np

from mpcmobo.systems.base import System
from mpcmobo.systems.parameterization import MPCSpec


def lq_dynamics(x: ca.SX, u: ca.SX, p: ca.SX) -> ca.SX:
    """Continuous dynamics of the damped oscillator: ``dp/dt = v``, ``dv/dt = -p0 p - p1 v + p2
    f``."""
    return ca.vertcat(x[1], -p[0] * x[0] - p[1] * x[1] + p[2] * u[0])


def make_lq(**spec_overrides: Any) -> System:
    """The LQ test system (a damped oscillator with a quadratic cost), ``spec_overrides`` applied to
    its MPC spec."""
    spec = MPCSpec(horizon=8, gamma=0.95, Gamma=np.full(2, 1e3), Gamma_f=np.full(2, 1e3))
    spec = spec.with_overrides("LQ system", **spec_overrides)
    return System(
        name="lq",
        description="Linear damped oscillator with quadratic cost (test bed)",
        state_names=("p", "v"),
        input_names=("f",),
        dynamics=lq_dynamics,
        param_names=("stiffness", "damping", "gain"),
        true_params=np.array([1.0, 0.5, 1.0]),
        models={"imperfect": np.array([1.3, 0.3, 0.8])},
        dt=0.1,
        x_ref=np.zeros(2),
        u_ref=np.zeros(1),
        x_lb=np.array([-10.0, -10.0]),
        x_ub=np.array([10.0, 10.0]),
        u_lb=np.array([-5.0]),
        u_ub=np.array([5.0]),
        Q=np.array([1.0, 0.5]),
        R=np.array([0.1]),
        Gamma=np.full(2, 1e3),
        x0_lb=np.array([-2.0, -1.0]),
        x0_ub=np.array([2.0, 1.0]),
        episode_steps=30,
        mpc_spec=spec,
    )
