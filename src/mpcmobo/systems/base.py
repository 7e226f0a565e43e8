"""A controlled system: true plant, imperfect model, constraints, references and the RL cost.

A :class:`System` holds everything the MPC and the learners need to know about a process and
nothing about how it is controlled. The CSTR of the paper is one instance
(:mod:`mpcmobo.systems.cstr`); a user-defined system is another, registered with
:func:`mpcmobo.systems.register_system`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from mpcmobo.systems.parameterization import MPCSpec, Parameterization
from mpcmobo.systems.space import SearchSpace

# f(x, u, p) -> dx/dt, written with CasADi symbols; p are the model parameters (the mismatch).
Dynamics = Callable[[ca.SX, ca.SX, ca.SX], ca.SX]


def rk4_step(f: Dynamics, x: ca.SX, u: ca.SX, p: ca.SX, dt: float, substeps: int = 1) -> ca.SX:
    """One explicit fourth-order Runge-Kutta step of ``dx/dt = f(x, u, p)`` over ``dt``."""
    h = dt / substeps
    for _ in range(substeps):
        k1 = f(x, u, p)
        k2 = f(x + h / 2 * k1, u, p)
        k3 = f(x + h / 2 * k2, u, p)
        k4 = f(x + h * k3, u, p)
        x = x + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    return x


def _half_span(lb: np.ndarray, ub: np.ndarray) -> np.ndarray:
    """Default variable scale: half the bound interval, 1 where it is infinite or empty."""
    span = ub - lb
    return np.where(np.isfinite(span) & (span > 0), span / 2, 1.0)


def _vec(a: ArrayLike, n: int, label: str) -> np.ndarray:
    """A float copy of ``a`` with ``n`` entries (a copy: a system never aliases its caller's
    arrays, e.g. the module constants ``cstr.TRUE_PARAMS``)."""
    a = np.array(a, dtype=float).reshape(-1)
    if a.shape != (n,):
        raise ValueError(f"{label} has {a.shape[0]} entries, expected {n}")
    return a


@dataclass(frozen=True)
class System:
    """A discrete-time control problem built from continuous dynamics and RK4.

    Frozen (fields cannot be reassigned, the arrays are the system's own copies): the derived
    :attr:`discrete_step` and :attr:`parameterization` are computed once per instance;
    :meth:`with_spec` (``dataclasses.replace``) makes a new instance that derives them afresh,
    and a pickled system carries them along.

    Parameters
    ----------
    dynamics:
        ``f(x, u, p)`` continuous-time right-hand side with CasADi expressions.
    true_params:
        Model parameters ``p`` of the true plant.
    models:
        Named parameter vectors for the MPC's prediction model, at least ``"perfect"``
        (equal to ``true_params``) and usually ``"imperfect"``.
    Q, R, Gamma:
        Weights of the RL stage cost ``L = |x-x_r|_Q^2 + |u-u_r|_R^2 + Gamma^T max(0, h(x))``,
        ``h`` the state bound violations (paper, section 5).
    x0_lb, x0_ub:
        Box of the uniform initial-state distribution.
    """

    name: str
    state_names: Sequence[str]
    input_names: Sequence[str]
    dynamics: Dynamics
    param_names: Sequence[str]
    true_params: np.ndarray
    models: dict[str, np.ndarray]
    dt: float
    x_ref: np.ndarray
    u_ref: np.ndarray
    x_lb: np.ndarray
    x_ub: np.ndarray
    u_lb: np.ndarray
    u_ub: np.ndarray
    Q: np.ndarray
    R: np.ndarray
    Gamma: np.ndarray
    x0_lb: np.ndarray
    x0_ub: np.ndarray
    episode_steps: int = 60
    substeps: int = 1
    mpc_spec: MPCSpec = field(default_factory=MPCSpec)
    x_scale: np.ndarray | None = None
    u_scale: np.ndarray | None = None
    description: str = ""

    # derived, not an argument: F(x, u, p) -> x_{k+1}, built once (``_rk4_function``)
    discrete_step: ca.Function = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        nx, nu, npar = len(self.state_names), len(self.input_names), len(self.param_names)
        normalised: dict = {
            "state_names": tuple(self.state_names),
            "input_names": tuple(self.input_names),
            "param_names": tuple(self.param_names),
        }
        for name in ("x_ref", "x_lb", "x_ub", "Q", "Gamma", "x0_lb", "x0_ub"):
            normalised[name] = _vec(getattr(self, name), nx, f"{self.name}.{name}")
        for name in ("u_ref", "u_lb", "u_ub", "R"):
            normalised[name] = _vec(getattr(self, name), nu, f"{self.name}.{name}")
        true_params = _vec(self.true_params, npar, f"{self.name}.true_params")
        models = {k: _vec(v, npar, f"{self.name} model '{k}'") for k, v in self.models.items()}
        models.setdefault("perfect", true_params.copy())
        normalised.update(true_params=true_params, models=models)
        for name, value in normalised.items():
            object.__setattr__(self, name, value)  # frozen: normalised once, here
        if np.any(self.u_lb > self.u_ub) or np.any(self.x_lb > self.x_ub):
            raise ValueError(f"{self.name}: a lower bound exceeds its upper bound")
        if self.dt <= 0:
            raise ValueError(f"{self.name}: dt must be positive, got {self.dt}")
        if self.x_scale is None:
            object.__setattr__(self, "x_scale", _half_span(self.x_lb, self.x_ub))
        if self.u_scale is None:
            object.__setattr__(self, "u_scale", _half_span(self.u_lb, self.u_ub))
        object.__setattr__(self, "discrete_step", self._rk4_function())

    # ------------------------------------------------------------------ sizes and names
    @property
    def nx(self) -> int:
        """Number of states."""
        return len(self.state_names)

    @property
    def nu(self) -> int:
        """Number of inputs."""
        return len(self.input_names)

    def _rk4_function(self) -> ca.Function:
        """``discrete_step``: ``F(x, u, p) -> x_{k+1}``, RK4 over one period ``dt``.

        The one discretisation of the dynamics: the true plant (``p`` = ``true_params``), the
        prediction model (eq. mpc_model) and the MPC's transcription all call it.
        """
        x = ca.SX.sym("x", self.nx)
        u = ca.SX.sym("u", self.nu)
        p = ca.SX.sym("p", len(self.param_names))
        xn = rk4_step(self.dynamics, x, u, p, self.dt, self.substeps)
        return ca.Function("step", [x, u, p], [xn])

    @cached_property
    def parameterization(self) -> Parameterization:
        """The learnable theta of the MPC: names, theta0, blocks and search space."""
        return Parameterization.from_system(self)

    @property
    def search_space(self) -> SearchSpace:
        """The search space of theta (from the cached MPC parameterization)."""
        return self.parameterization.space

    def with_spec(self, **changes: Any) -> System:
        """A copy of the system with a modified MPC parameterization."""
        return replace(self, mpc_spec=replace(self.mpc_spec, **changes))

    # ------------------------------------------------------------------ validation
    def check_state(self, x: ArrayLike) -> np.ndarray:
        """``x`` as a flat float vector of length ``nx``; a wrong shape or a non-finite value is a
        ``ValueError``."""
        x = np.asarray(x, dtype=float)
        if x.shape not in ((self.nx,), (self.nx, 1)):
            raise ValueError(f"state has shape {x.shape}, expected ({self.nx},) for {self.name}")
        x = x.reshape(-1)
        if not np.all(np.isfinite(x)):
            raise ValueError(f"state contains NaN or inf: {x}")
        return x

    def check_input(self, u: ArrayLike) -> np.ndarray:
        """``u`` as a flat float vector of length ``nu``; a wrong shape or a non-finite value is a
        ``ValueError``."""
        u = np.asarray(u, dtype=float)
        if u.shape not in ((self.nu,), (self.nu, 1)):
            raise ValueError(f"input has shape {u.shape}, expected ({self.nu},) for {self.name}")
        u = u.reshape(-1)
        if not np.all(np.isfinite(u)):
            raise ValueError(f"input contains NaN or inf: {u}")
        return u

    def model_params(self, model: str | np.ndarray) -> np.ndarray:
        """The model parameter vector p of a named model (``true``, ``imperfect``, ...) or of an
        array."""
        if isinstance(model, str):
            if model not in self.models:
                raise ValueError(
                    f"unknown model '{model}' for {self.name}; known: {sorted(self.models)}"
                )
            return self.models[model]
        return _vec(model, len(self.param_names), "model parameters")

    # ------------------------------------------------------------------ plant and cost
    def plant_step(self, x: ArrayLike, u: ArrayLike) -> np.ndarray:
        """The true plant over one sampling period: ``x_{k+1} = f(x_k, u_k)``."""
        return np.asarray(
            self.discrete_step(self.check_state(x), self.check_input(u), self.true_params)
        ).reshape(-1)

    def model_step(
        self, x: ArrayLike, u: ArrayLike, model: str | np.ndarray = "imperfect"
    ) -> np.ndarray:
        """The MPC's prediction model ``x_{k+1} = f_hat(x_k, u_k)`` (eq. mpc_model)."""
        p = self.model_params(model)
        x, u = self.check_state(x), self.check_input(u)
        return np.asarray(self.discrete_step(x, u, p)).reshape(-1)

    def constraint_violation(self, x: ArrayLike, u: ArrayLike | None = None) -> float:
        """Sum of the positive parts of the state-bound violations ``max(0, h(x))``."""
        x = np.asarray(x, dtype=float).reshape(-1)
        return float(np.sum(np.maximum(0, self.x_lb - x) + np.maximum(0, x - self.x_ub)))

    def stage_cost(self, x: ArrayLike, u: ArrayLike) -> float:
        """RL stage cost L(x, u) of section 5: weighted squared error plus violation penalty."""
        x, u = self.check_state(x), self.check_input(u)
        dx, du = x - self.x_ref, u - self.u_ref
        viol = np.maximum(0, self.x_lb - x) + np.maximum(0, x - self.x_ub)
        return float(dx @ (self.Q * dx) + du @ (self.R * du) + self.Gamma @ viol)

    def sample_initial_state(self, rng: np.random.Generator) -> np.ndarray:
        """A draw of the (uniform, box) initial-state distribution."""
        return rng.uniform(self.x0_lb, self.x0_ub)

    def clip_input(self, u: ArrayLike) -> np.ndarray:
        """``u`` clipped to the input bounds."""
        return np.clip(np.asarray(u, dtype=float).reshape(-1), self.u_lb, self.u_ub)
