"""Sources of user-defined systems and plants that the tests write into temporary files: a
system is then found by its path, ``file.py:make_system``, as a user's would be."""

from pathlib import Path

SYSTEM = '''
import casadi as ca
import numpy as np

from mpcmobo.systems import MPCSpec, System

DT = 0.2


def step(x, u, p):
    """A discrete double integrator with an input gain p[0] (the model's error)."""
    v = x[1] + DT * p[0] * u[0]
    return ca.vertcat(x[0] + DT * x[1] + 0.5 * DT**2 * p[0] * u[0], v)


def make_system(true_params=(1.0,), imperfect=(0.6,), path=True):
    return System(
        name="double_integrator",
        description="discrete double integrator, gain error, a non-box constraint",
        state_names=("pos", "vel"),
        input_names=("force",),
        dynamics=step,
        discrete_time=True,
        param_names=("gain",),
        true_params=None if true_params is None else np.array(true_params),
        models={"imperfect": np.array(imperfect)},
        dt=DT,
        x_ref=np.zeros(2),
        u_ref=np.zeros(1),
        x_lb=np.array([-5.0, -5.0]),
        x_ub=np.array([5.0, 5.0]),
        u_lb=np.array([-2.0]),
        u_ub=np.array([2.0]),
        Q=np.array([1.0, 0.2]),
        R=np.array([0.1]),
        Gamma=np.full(2, 100.0),
        path_constraints=(lambda x, u: ca.vertcat(x[0] + 0.5 * x[1] - 1.5)) if path else None,
        x0_lb=np.array([-1.5, -0.5]),
        x0_ub=np.array([1.5, 0.5]),
        episode_steps=8,
        mpc_spec=MPCSpec(horizon=5, gamma=0.95, Gamma=np.full(2, 100.0), Gamma_f=np.full(2, 100.0)),
    )


def make_model():
    """The model only: no true parameters, no perfect model (J* is absent)."""
    return make_system(true_params=None)


def make_wrong_type():
    return {"not": "a system"}


def make_broadcast():
    """A dynamics function with 1 entry for 2 states (was silently broadcast)."""
    import dataclasses
    s = make_system()
    return System(**{f.name: getattr(s, f.name) for f in dataclasses.fields(s) if f.init}
                  | {"dynamics": lambda x, u, p: x[0] + u[0]})
'''

PLANT = '''
import gymnasium
import numpy as np
from gymnasium import spaces


class Integrator(gymnasium.Env):
    """Not a mpcmobo system: a double integrator with a small seeded input disturbance."""

    def __init__(self, n_obs=2):
        self.observation_space = spaces.Box(-np.inf, np.inf, (n_obs,), np.float64)
        self.action_space = spaces.Box(-2.0, 2.0, (1,), np.float64)
        self.x = np.zeros(n_obs)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        x0 = (options or {}).get("x0")
        self.x = np.array(x0 if x0 is not None else self.np_random.uniform(-1, 1, 2), float)
        return self.x.copy(), {}

    def step(self, u):
        u = float(np.asarray(u).reshape(-1)[0]) + 0.01 * self.np_random.standard_normal()
        p, v = self.x
        cost = p**2 + 0.2 * v**2 + 0.1 * u**2
        self.x = np.array([p + 0.2 * v + 0.02 * u, v + 0.2 * u])
        return self.x.copy(), -cost, False, False, {"stage_cost": cost, "violation": 0.0}


def make_env():
    return Integrator()


def make_env_3():
    return Integrator(n_obs=3)


class Stubborn(Integrator):
    """Starts at the origin whatever options['x0'] says."""

    def reset(self, *, seed=None, options=None):
        return super().reset(seed=seed, options={"x0": [0.0, 0.0]})


def make_stubborn_env():
    return Stubborn()
'''


BROKEN = {
    "broken.py": "def make_system(:\n",  # a syntax error
    "raises.py": "raise RuntimeError('this file does not import')\n",
}


def write_user_files(d: Path) -> Path:
    """Write the system, the plant and the files that do not import into directory ``d``."""
    (d / "usersys.py").write_text(SYSTEM)
    (d / "userplant.py").write_text(PLANT)
    for name, source in BROKEN.items():
        (d / name).write_text(source)
    return d
