"""A controlled system: the MPC's model, constraints, references, the RL cost, and the plant.

A :class:`System` holds everything the MPC and the learners need to know about a process and
nothing about how it is controlled. The CSTR of the paper is one instance
(:mod:`mpcmobo.systems.cstr`); a user-defined system is another, built by a factory that the
command line finds by name (``mpcmobo run --system pkg.mod:make_system``, see
:mod:`mpcmobo.systems.registry`).

The model is continuous (``dynamics`` is ``dx/dt = f(x, u, p)``, discretised by RK4) or
discrete (``discrete_time=True``: ``dynamics`` is the map ``x+ = F(x, u, p)``, used as it is).
Besides the state bounds, ``path_constraints`` adds general constraints ``h(x, u) <= 0``; the
MPC relaxes them with l1 slacks, the RL cost penalises their violation with ``Gamma_h``.
The plant is the same equations with ``true_params`` (:mod:`mpcmobo.systems.plant` wraps it as
a gymnasium environment), or any other gymnasium environment given to the study; without
``true_params`` and without a ``"perfect"`` model, J* is absent.

Every field is checked when the system is built (:class:`SystemDefinitionError` names it).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any

import casadi as ca
import numpy as np
from numpy.typing import ArrayLike

from mpcmobo.systems.parameterization import MPCSpec, Parameterization
from mpcmobo.systems.space import SearchSpace

# f(x, u, p) -> dx/dt (or x+ with discrete_time), written with CasADi symbols; p are the model
# parameters (the mismatch).
Dynamics = Callable[[ca.SX, ca.SX, ca.SX], ca.SX]
# h(x, u) -> (nh,) general path constraints h <= 0
PathConstraints = Callable[[ca.SX, ca.SX], ca.SX]


class SystemDefinitionError(ValueError):
    """A system that cannot be built: the message names the system and the field."""


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


def _vec(a: ArrayLike, n: int, label: str, finite: bool = False) -> np.ndarray:
    """A float copy of ``a`` with ``n`` entries (a copy: a system never aliases its caller's
    arrays, e.g. the module constants ``cstr.TRUE_PARAMS``)."""
    try:
        a = np.array(a, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise SystemDefinitionError(f"{label} must be {n} numbers, got {a!r}") from None
    if a.shape != (n,):
        raise SystemDefinitionError(f"{label} has {a.shape[0]} entries, expected {n}")
    if finite and not np.all(np.isfinite(a)):
        raise SystemDefinitionError(f"{label} must be finite, got {a.tolist()}")
    if np.any(np.isnan(a)):
        raise SystemDefinitionError(f"{label} contains NaN: {a.tolist()}")
    return a


def _names(value: Any, label: str, allow_empty: bool = False) -> tuple[str, ...]:
    """Names as a tuple of distinct non-empty strings."""
    if isinstance(value, str):
        raise SystemDefinitionError(f"{label} must be a list of names, got the string {value!r}")
    try:
        names = tuple(value)
    except TypeError:
        raise SystemDefinitionError(f"{label} must be a list of names, got {value!r}") from None
    if not names and not allow_empty:
        raise SystemDefinitionError(f"{label} is empty")
    for n in names:
        if not isinstance(n, str) or not n:
            raise SystemDefinitionError(f"{label} must be non-empty strings, got {n!r}")
    if len(set(names)) != len(names):
        raise SystemDefinitionError(f"{label} has a repeated name: {list(names)}")
    return names


def _sx_output(
    fn: Callable[..., Any], args: Sequence[Any], label: str, n: int | None, expected: str
) -> ca.SX:
    """Call ``fn`` on CasADi symbols; its output as an SX column of ``n`` rows (if given)."""
    try:
        out = fn(*args)
        if isinstance(out, (list, tuple)):
            out = ca.vertcat(*out)
        out = ca.SX(out)
    except Exception as err:  # noqa: BLE001 - any failure of user code is reported here
        raise SystemDefinitionError(
            f"{label} cannot be evaluated on CasADi symbols: {type(err).__name__}: "
            + " ".join(str(err).split())  # one line
        ) from None
    if out.shape[1] != 1 and out.shape[0] == 1:
        out = out.T
    if out.shape[1] != 1 or (n is not None and out.shape[0] != n):
        raise SystemDefinitionError(f"{label} returns shape {out.shape}, expected ({expected}, 1)")
    return out


@dataclass(frozen=True)
class System:
    """A discrete-time control problem: the MPC's model, constraints, references, RL cost.

    Frozen (fields cannot be reassigned, the arrays are the system's own copies): the derived
    :attr:`discrete_step` and :attr:`parameterization` are computed once per instance;
    :meth:`with_spec` (``dataclasses.replace``) makes a new instance that derives them afresh,
    and a pickled system carries them along.

    Parameters
    ----------
    dynamics:
        ``f(x, u, p)`` with CasADi expressions: the continuous-time right-hand side
        ``dx/dt`` (discretised by RK4 over ``dt`` with ``substeps``), or, with
        ``discrete_time=True``, the discrete map ``x_{k+1} = F(x_k, u_k, p)``.
    true_params:
        Model parameters ``p`` of the true plant, or None when the plant is not these equations
        (a gymnasium environment given to the study is then the plant).
    models:
        Named parameter vectors for the MPC's prediction model: ``"imperfect"`` (the MPC's
        model, required) and, if known, ``"perfect"`` (the reference model of J*; default
        ``true_params`` when they are given). Without a perfect model J* is absent.
    Q, R, Gamma:
        Weights of the RL stage cost ``L = |x-x_r|_Q^2 + |u-u_r|_R^2 + Gamma^T max(0, h(x))
        + Gamma_h^T max(0, h(x, u))``, ``h(x)`` the state bound violations (paper, section 5).
    x0_lb, x0_ub:
        Box of the uniform initial-state distribution, inside the state bounds.
    path_constraints:
        Optional ``h(x, u) -> (nh,)`` CasADi expression, constraints ``h(x, u) <= 0`` besides
        the bounds (relaxed with l1 slacks in the MPC, penalised with ``Gamma_h`` in L).
    identifiable:
        The model parameters identification fits (``[system] identify = true``); default all
        of ``param_names``. The others are structure the identification keeps at the MPC's
        model values.
    constraint_names, Gamma_h, h_scale:
        Names (default ``h0, h1, ...``), RL penalty (default the largest ``Gamma``) and MPC
        slack scale (default 1) of each path constraint.
    """

    name: str
    state_names: Sequence[str]
    input_names: Sequence[str]
    dynamics: Dynamics
    param_names: Sequence[str]
    true_params: np.ndarray | None
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
    discrete_time: bool = False
    path_constraints: PathConstraints | None = None
    constraint_names: Sequence[str] = ()
    Gamma_h: np.ndarray | None = None
    h_scale: np.ndarray | None = None
    identifiable: Sequence[str] | None = None

    # derived, not an argument: F(x, u, p) -> x_{k+1}, built once (``_step_function``)
    discrete_step: ca.Function = field(init=False, repr=False, compare=False)
    # derived: h(x, u) -> (nh,), None without path constraints
    path_function: ca.Function | None = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise SystemDefinitionError(
                f"System.name must be a non-empty string, got {self.name!r}"
            )
        nm = self.name
        set_ = object.__setattr__  # frozen: normalised once, here
        for key in ("state_names", "input_names"):
            set_(self, key, _names(getattr(self, key), f"{nm}.{key}"))
        set_(self, "param_names", _names(self.param_names, f"{nm}.param_names", allow_empty=True))
        ident = self.param_names if self.identifiable is None else self.identifiable
        ident = _names(ident, f"{nm}.identifiable", allow_empty=True)
        unknown = [n for n in ident if n not in self.param_names]
        if unknown:
            raise SystemDefinitionError(
                f"{nm}.identifiable names unknown model parameters {unknown}; the system has "
                f"{list(self.param_names)}"
            )
        set_(self, "identifiable", ident)
        nx, nu, npar = len(self.state_names), len(self.input_names), len(self.param_names)
        finite = ("x_ref", "u_ref", "Q", "R", "Gamma", "x0_lb", "x0_ub")
        for key in ("x_ref", "x_lb", "x_ub", "Q", "Gamma", "x0_lb", "x0_ub"):
            set_(self, key, _vec(getattr(self, key), nx, f"{nm}.{key}", key in finite))
        for key in ("u_ref", "u_lb", "u_ub", "R"):
            set_(self, key, _vec(getattr(self, key), nu, f"{nm}.{key}", key in finite))
        self._check_numbers()
        self._check_models(npar)
        if self.x_scale is None:
            set_(self, "x_scale", _half_span(self.x_lb, self.x_ub))
        if self.u_scale is None:
            set_(self, "u_scale", _half_span(self.u_lb, self.u_ub))
        for key, n in (("x_scale", nx), ("u_scale", nu)):
            v = _vec(getattr(self, key), n, f"{nm}.{key}", finite=True)
            if np.any(v <= 0):
                raise SystemDefinitionError(f"{nm}.{key} must be positive, got {v.tolist()}")
            set_(self, key, v)
        set_(self, "discrete_step", self._step_function())
        set_(self, "path_function", self._path_function())

    def _check_numbers(self) -> None:
        """Bounds ordered, the initial-state box inside the state bounds, weights positive."""
        nm = self.name
        for lo, hi, names in (
            ("x_lb", "x_ub", self.state_names),
            ("u_lb", "u_ub", self.input_names),
            ("x0_lb", "x0_ub", self.state_names),
        ):
            bad = np.flatnonzero(getattr(self, lo) > getattr(self, hi))
            if bad.size:
                j = int(bad[0])
                raise SystemDefinitionError(
                    f"{nm}.{lo} exceeds {nm}.{hi} for '{names[j]}': "
                    f"{getattr(self, lo)[j]} > {getattr(self, hi)[j]}"
                )
        outside = np.flatnonzero((self.x0_lb < self.x_lb) | (self.x0_ub > self.x_ub))
        if outside.size:
            j = int(outside[0])
            raise SystemDefinitionError(
                f"{nm}.x0_lb/x0_ub: the initial-state box [{self.x0_lb[j]}, {self.x0_ub[j]}] of "
                f"'{self.state_names[j]}' is not inside the state bounds "
                f"[{self.x_lb[j]}, {self.x_ub[j]}]"
            )
        for key, names in (("Q", self.state_names), ("R", self.input_names)):
            v = getattr(self, key)
            if np.any(v <= 0):
                j = int(np.flatnonzero(v <= 0)[0])
                raise SystemDefinitionError(
                    f"{nm}.{key} must be positive (the MPC searches its weights in log scale), "
                    f"got {v[j]} for '{names[j]}'"
                )
        if np.any(self.Gamma < 0):
            raise SystemDefinitionError(f"{nm}.Gamma must be >= 0, got {self.Gamma.tolist()}")
        if not (isinstance(self.dt, (int, float)) and math.isfinite(self.dt) and self.dt > 0):
            raise SystemDefinitionError(f"{nm}.dt must be a positive number, got {self.dt!r}")
        for key in ("episode_steps", "substeps"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise SystemDefinitionError(f"{nm}.{key} must be an integer >= 1, got {v!r}")
        if not callable(self.dynamics):
            raise SystemDefinitionError(f"{nm}.dynamics must be a function f(x, u, p)")
        if self.path_constraints is not None and not callable(self.path_constraints):
            raise SystemDefinitionError(f"{nm}.path_constraints must be a function h(x, u)")

    def _check_models(self, npar: int) -> None:
        """``true_params`` and the named models: parameter vectors; "imperfect" is required."""
        nm = self.name
        true_params = None
        if self.true_params is not None:
            true_params = _vec(self.true_params, npar, f"{nm}.true_params", finite=True)
        if not isinstance(self.models, Mapping):
            raise SystemDefinitionError(
                f"{nm}.models must be a table {{name: parameters}}, got {self.models!r}"
            )
        models = {}
        for k, v in self.models.items():
            if not isinstance(k, str) or not k:
                raise SystemDefinitionError(
                    f"{nm}.models: a model name must be a string, got {k!r}"
                )
            models[k] = _vec(v, npar, f"{nm}.models['{k}']", finite=True)
        if "imperfect" not in models:
            raise SystemDefinitionError(
                f"{nm}.models needs 'imperfect' (the MPC's model); got {sorted(models)}"
            )
        if true_params is not None:
            models.setdefault("perfect", true_params.copy())
        object.__setattr__(self, "true_params", true_params)
        object.__setattr__(self, "models", models)

    # ------------------------------------------------------------------ sizes and names
    @property
    def nx(self) -> int:
        """Number of states."""
        return len(self.state_names)

    @property
    def nu(self) -> int:
        """Number of inputs."""
        return len(self.input_names)

    @property
    def nh(self) -> int:
        """Number of general path constraints h(x, u) <= 0."""
        return 0 if self.path_function is None else int(self.path_function.size1_out(0))

    @property
    def has_true_plant(self) -> bool:
        """Whether the plant is these equations with ``true_params``."""
        return self.true_params is not None

    @property
    def has_reference_model(self) -> bool:
        """Whether a perfect model (the MPC of J*) is known."""
        return "perfect" in self.models

    def _step_function(self) -> ca.Function:
        """``discrete_step``: ``F(x, u, p) -> x_{k+1}``: RK4 over one period ``dt`` of the
        continuous dynamics, or the discrete map itself (``discrete_time``).

        The one discretisation of the dynamics: the true plant (``p`` = ``true_params``), the
        prediction model (eq. mpc_model) and the MPC's transcription all call it.
        """
        x = ca.SX.sym("x", self.nx)
        u = ca.SX.sym("u", self.nu)
        p = ca.SX.sym("p", len(self.param_names))
        kind = "discrete map x+ = F(x, u, p)" if self.discrete_time else "f(x, u, p) = dx/dt"
        label = f"{self.name}.dynamics ({kind})"
        out = _sx_output(self.dynamics, (x, u, p), label, self.nx, f"{self.nx} states")
        if self.discrete_time:
            xn = out
        else:
            xn = rk4_step(self.dynamics, x, u, p, self.dt, self.substeps)
        return ca.Function("step", [x, u, p], [xn])

    def _path_function(self) -> ca.Function | None:
        """``h(x, u)`` as a CasADi function, with its names, penalties and scales checked."""
        nm = self.name
        if self.path_constraints is None:
            for key in ("Gamma_h", "h_scale"):
                if getattr(self, key) is not None:
                    raise SystemDefinitionError(f"{nm}.{key} is given without path_constraints")
            if tuple(self.constraint_names):
                raise SystemDefinitionError(
                    f"{nm}.constraint_names is given without path_constraints"
                )
            object.__setattr__(self, "constraint_names", ())
            return None
        x = ca.SX.sym("x", self.nx)
        u = ca.SX.sym("u", self.nu)
        names = tuple(self.constraint_names)
        n = len(names) if names else None
        expected = f"{n} constraints (constraint_names)" if names else "nh"
        h = _sx_output(self.path_constraints, (x, u), f"{nm}.path_constraints", n, expected)
        nh = h.shape[0]
        if nh == 0:
            raise SystemDefinitionError(f"{nm}.path_constraints returns no constraint")
        names = _names(names or [f"h{i}" for i in range(nh)], f"{nm}.constraint_names")
        object.__setattr__(self, "constraint_names", names)
        default_gamma = float(np.max(self.Gamma)) if self.Gamma.size else 1e3
        G = np.full(nh, default_gamma) if self.Gamma_h is None else self.Gamma_h
        G = _vec(G, nh, f"{nm}.Gamma_h", finite=True)
        if np.any(G < 0):
            raise SystemDefinitionError(f"{nm}.Gamma_h must be >= 0, got {G.tolist()}")
        S = _vec(np.ones(nh) if self.h_scale is None else self.h_scale, nh, f"{nm}.h_scale", True)
        if np.any(S <= 0):
            raise SystemDefinitionError(f"{nm}.h_scale must be positive, got {S.tolist()}")
        object.__setattr__(self, "Gamma_h", G)
        object.__setattr__(self, "h_scale", S)
        return ca.Function("h", [x, u], [h])

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
        if self.true_params is None:
            raise ValueError(
                f"{self.name} has no true plant (true_params is None): give the study a plant "
                "environment ([system] plant)"
            )
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

    def path_values(self, x: ArrayLike, u: ArrayLike) -> np.ndarray:
        """``h(x, u)`` of the path constraints (empty without them)."""
        if self.path_function is None:
            return np.zeros(0)
        x = np.asarray(x, dtype=float).reshape(-1)
        u = np.asarray(u, dtype=float).reshape(-1)
        return np.asarray(self.path_function(x, u)).reshape(-1)

    def constraint_violation(self, x: ArrayLike, u: ArrayLike | None = None) -> float:
        """Sum of the positive parts of the state-bound violations ``max(0, h(x))`` and, given
        ``u``, of the path constraints ``max(0, h(x, u))``."""
        x = np.asarray(x, dtype=float).reshape(-1)
        v = float(np.sum(np.maximum(0, self.x_lb - x) + np.maximum(0, x - self.x_ub)))
        if self.path_function is not None and u is not None:
            v += float(np.sum(np.maximum(0, self.path_values(x, u))))
        return v

    def stage_cost(self, x: ArrayLike, u: ArrayLike) -> float:
        """RL stage cost L(x, u) of section 5: weighted squared error plus violation penalty."""
        x, u = self.check_state(x), self.check_input(u)
        dx, du = x - self.x_ref, u - self.u_ref
        viol = np.maximum(0, self.x_lb - x) + np.maximum(0, x - self.x_ub)
        L = float(dx @ (self.Q * dx) + du @ (self.R * du) + self.Gamma @ viol)
        if self.path_function is not None:
            L += float(self.Gamma_h @ np.maximum(0, self.path_values(x, u)))
        return L

    def sample_initial_state(self, rng: np.random.Generator) -> np.ndarray:
        """A draw of the (uniform, box) initial-state distribution."""
        return rng.uniform(self.x0_lb, self.x0_ub)

    def clip_input(self, u: ArrayLike) -> np.ndarray:
        """``u`` clipped to the input bounds."""
        return np.clip(np.asarray(u, dtype=float).reshape(-1), self.u_lb, self.u_ub)
