"""A cart-pole held upright: a user-defined system for mpcmobo, outside the package.

Different in kind from the paper's CSTR: mechanical, open-loop unstable, fast (dt = 0.05 s),
with a *discrete-time* model and a *non-box* constraint.

- ``make_system()`` is the MPC's side: a discrete model ``x+ = F(x, u, p)`` (one semi-implicit
  Euler step of the cart-pole equations; ``discrete_time=True``, no RK4 around it), whose
  parameters ``p`` = (pole mass, pole half-length, cart mass) are wrong in the "imperfect"
  model; the "perfect" model (the reference of J*) is the same Euler map with the true masses
  and length. The path constraint keeps the pole's tip above the track:
  ``|cart position + 2 l sin(angle)| <= 0.8`` (two rows ``h(x, u) <= 0``, nonlinear in x).
- ``make_plant()`` is the plant: a gymnasium environment integrating the continuous equations
  with RK4 (10 substeps per period) and the true parameters; it is not a mpcmobo system. Its
  observation is the measured state; ``info`` carries the stage cost and the violation.

Run it from the command line (from the repository's root)::

    mpcmobo run --config examples/cartpole.toml --out runs/cartpole

or give the factory directly: ``mpcmobo run --system examples/cartpole.py:make_system``
(the plant is then the system's own discrete equations with the true parameters).
"""

from __future__ import annotations

import casadi as ca
import gymnasium
import numpy as np
from gymnasium import spaces

from mpcmobo.systems import MPCSpec, System

G = 9.81
TRUE = np.array([0.1, 0.5, 1.0])  # pole mass [kg], pole half-length [m], cart mass [kg]
WRONG = np.array([0.05, 0.7, 1.3])  # the MPC's imperfect model: a longer pole, a heavier cart
DT = 0.05  # sampling period [s]
TIP_LIMIT = 0.8  # |position of the pole's tip| <= 0.8 m
L_NOMINAL = TRUE[1]  # the constraint is written with the nominal length


def accelerations(x, u, p):
    """Cart and pole accelerations of the classic cart-pole (angle 0 = upright)."""
    m, ell, M = p[0], p[1], p[2]
    phi, omega = x[2], x[3]
    s, c = ca.sin(phi), ca.cos(phi)
    total = M + m
    tmp = (u[0] + m * ell * omega**2 * s) / total
    phi_dd = (G * s - c * tmp) / (ell * (4.0 / 3.0 - m * c**2 / total))
    p_dd = tmp - m * ell * phi_dd * c / total
    return p_dd, phi_dd


def euler_map(x, u, p):
    """The MPC's discrete model: one semi-implicit Euler step of length DT."""
    p_dd, phi_dd = accelerations(x, u, p)
    v = x[1] + DT * p_dd
    omega = x[3] + DT * phi_dd
    return ca.vertcat(x[0] + DT * v, v, x[2] + DT * omega, omega)


def tip_constraints(x, u):
    """h(x, u) <= 0: the tip of the pole stays within +-TIP_LIMIT of the track's centre."""
    tip = x[0] + 2 * L_NOMINAL * ca.sin(x[2])
    return ca.vertcat(tip - TIP_LIMIT, -tip - TIP_LIMIT)


def make_system() -> System:
    """The cart-pole as the MPC sees it: discrete model, bounds, tip constraint, RL cost."""
    return System(
        name="cartpole",
        description="Cart-pole held upright; discrete Euler model, tip-position constraint",
        state_names=("pos", "vel", "angle", "rate"),
        input_names=("force",),
        dynamics=euler_map,
        discrete_time=True,
        param_names=("pole_mass", "half_length", "cart_mass"),
        true_params=TRUE,
        models={"imperfect": WRONG},
        dt=DT,
        x_ref=np.zeros(4),
        u_ref=np.zeros(1),
        x_lb=np.array([-1.0, -3.0, -0.7, -5.0]),
        x_ub=np.array([1.0, 3.0, 0.7, 5.0]),
        u_lb=np.array([-15.0]),
        u_ub=np.array([15.0]),
        Q=np.array([5.0, 0.5, 20.0, 0.5]),
        R=np.array([0.05]),
        Gamma=np.full(4, 1e3),
        path_constraints=tip_constraints,
        constraint_names=("tip_right", "tip_left"),
        Gamma_h=np.full(2, 1e3),
        h_scale=np.full(2, 0.5),
        x0_lb=np.array([-0.4, -0.3, -0.25, -0.3]),
        x0_ub=np.array([0.4, 0.3, 0.25, 0.3]),
        episode_steps=40,
        mpc_spec=MPCSpec(
            horizon=10,
            gamma=0.97,
            Gamma=np.full(4, 1e3),
            Gamma_f=np.full(4, 1e3),
            T0=10 * np.array([5.0, 0.5, 20.0, 0.5]),  # terminal weights: 10 x the stage weights
        ),
    )


def _rhs(x, u, p):
    p_dd, phi_dd = accelerations(x, u, p)
    return ca.vertcat(x[1], p_dd, x[3], phi_dd)


class CartPolePlant(gymnasium.Env):
    """The true cart-pole: RK4 of the continuous equations (10 substeps per period)."""

    metadata = {"render_modes": []}

    def __init__(self, substeps: int = 10) -> None:
        self.system = make_system()  # for its bounds, initial-state box and RL stage cost
        x, u = ca.SX.sym("x", 4), ca.SX.sym("u", 1)
        h = DT / substeps
        xn = x
        for _ in range(substeps):
            k1 = _rhs(xn, u, TRUE)
            k2 = _rhs(xn + h / 2 * k1, u, TRUE)
            k3 = _rhs(xn + h / 2 * k2, u, TRUE)
            k4 = _rhs(xn + h * k3, u, TRUE)
            xn = xn + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        self._step = ca.Function("plant", [x, u], [xn])
        self.observation_space = spaces.Box(-np.inf, np.inf, (4,), np.float64)
        self.action_space = spaces.Box(-15.0, 15.0, (1,), np.float64)
        self._x: np.ndarray | None = None

    def reset(self, *, seed=None, options=None):
        """Start at ``options["x0"]`` if given, else at a draw of the initial-state box."""
        super().reset(seed=seed)
        x0 = (options or {}).get("x0")
        if x0 is None:
            x0 = self.system.sample_initial_state(self.np_random)
        self._x = np.array(x0, dtype=float)
        return self._x.copy(), {}

    def step(self, action):
        """One period of the true cart-pole; ``info`` carries the stage cost and violation."""
        u = np.clip(np.asarray(action, dtype=float).reshape(1), -15.0, 15.0)
        x = self._x
        cost = self.system.stage_cost(x, u)
        violation = self.system.constraint_violation(x, u)
        self._x = np.asarray(self._step(x, u)).reshape(-1)
        info = {"stage_cost": cost, "violation": violation}
        return self._x.copy(), -cost, False, False, info


def make_plant() -> CartPolePlant:
    """The plant factory named in ``examples/cartpole.toml`` (``[system] plant``)."""
    return CartPolePlant()
