"""The learnable parameter vector theta of the MPC (eq. V0 with the cost of section 5)."""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import ArrayLike

from mpcmobo.systems.space import SearchSpace

if TYPE_CHECKING:  # pragma: no cover
    from mpcmobo.systems.base import System


@dataclass
class MPCSpec:
    """How the MPC of eq. (V0) is parameterised for a system: a setting, not code.

    The learnable vector theta is, in this order (each block optional where noted):

    ``theta_c`` (1), ``T_<x>`` terminal weights (nx), ``G_<x>``, ``G_<u>`` linear terms (nx+nu),
    ``Q_<x>`` stage state weights (nx), ``R_<u>`` stage input weights (nu), then the model
    parameters listed in ``learn_model`` (``model_<name>``) and, if ``learn_backoff``, state
    constraint back-offs ``b_lb_<x>``, ``b_ub_<x>`` (2 nx).
    """

    horizon: int = 10
    gamma: float = 0.99
    Gamma: np.ndarray | None = None  # slack penalties of the stage constraints (nx,)
    Gamma_f: np.ndarray | None = None  # slack penalties of the terminal constraints (nx,)
    Q0: np.ndarray | None = None  # initial stage weights (default: the RL stage cost's)
    R0: np.ndarray | None = None
    T0: np.ndarray | None = None  # initial terminal weights (default: Q0)
    weight_log_range: float = 4.0  # search bounds theta0 * exp(+-range) for the weights
    G_bound: np.ndarray | None = None  # |G| bounds (nx+nu,)
    theta_c_bound: float = 1e4
    learn_theta_c: bool = False  # theta_c never changes the policy; searched only if True
    learn_model: tuple[str, ...] = ()  # names of model parameters made learnable
    model_log_range: float = 0.7
    learn_backoff: bool = False
    backoff_max: np.ndarray | None = None  # upper bound of each back-off (nx,)

    def with_overrides(self, owner: str = "system", **overrides: Any) -> MPCSpec:
        """A copy with some settings changed; an unknown setting is a ValueError."""
        for k in overrides:
            if not hasattr(self, k):
                raise ValueError(f"unknown MPC setting '{k}' for the {owner}")
        return replace(self, **overrides)


@dataclass(frozen=True)
class Parameterization:
    """Names, default values, blocks (index slices) and search space of theta."""

    names: tuple[str, ...]
    theta0: np.ndarray
    blocks: dict[str, slice]
    space: SearchSpace
    model_param_index: tuple[int, ...]  # which model parameters are learnable, in block order

    @property
    def n_theta(self) -> int:
        """Number of parameters in theta."""
        return len(self.names)

    @classmethod
    def from_system(cls, system: System) -> Parameterization:
        """theta in block order (see :class:`MPCSpec`), its theta0 and its search box."""
        spec = system.mpc_spec
        xs, us = system.state_names, system.input_names
        Q0, R0, T0, G_bound = _initial_weights(system, spec)
        r = spec.weight_log_range
        b = _Blocks()
        b.add(
            "theta_c",
            ["theta_c"],
            [0.0],
            [-spec.theta_c_bound],
            [spec.theta_c_bound],
            False,
            not spec.learn_theta_c,
        )
        b.add("T", [f"T_{s}" for s in xs], T0, T0 * np.exp(-r), T0 * np.exp(r), True, False)
        G0 = np.zeros(system.nx + system.nu)
        b.add("G", [f"G_{s}" for s in (*xs, *us)], G0, -G_bound, G_bound, False, False)
        b.add("Q", [f"Q_{s}" for s in xs], Q0, Q0 * np.exp(-r), Q0 * np.exp(r), True, False)
        b.add("R", [f"R_{s}" for s in us], R0, R0 * np.exp(-r), R0 * np.exp(r), True, False)
        idx = _add_model_block(b, system, spec) if spec.learn_model else []
        if spec.learn_backoff:
            _add_backoff_block(b, system, spec)
        space = SearchSpace(
            b.names,
            np.concatenate(b.lo),
            np.concatenate(b.hi),
            np.concatenate(b.log),
            np.concatenate(b.fixed),
        )
        return cls(tuple(b.names), np.concatenate(b.theta0), b.blocks, space, tuple(idx))


@dataclass
class _Blocks:
    """theta as it is assembled: names, theta0, bounds, log and fixed flags, block slices."""

    names: list[str] = field(default_factory=list)
    theta0: list[np.ndarray] = field(default_factory=list)
    lo: list[np.ndarray] = field(default_factory=list)
    hi: list[np.ndarray] = field(default_factory=list)
    log: list[np.ndarray] = field(default_factory=list)
    fixed: list[np.ndarray] = field(default_factory=list)
    blocks: dict[str, slice] = field(default_factory=dict)

    def add(
        self,
        block: str,
        nm: list[str],
        v0: ArrayLike,
        l: ArrayLike,
        h: ArrayLike,
        lg: bool | ArrayLike,
        fx: bool | ArrayLike,
    ) -> None:
        """Append block ``block`` with names ``nm``, theta0 ``v0``, bounds [l, h], log scale
        ``lg`` and fixed flag ``fx`` (scalars or one per name)."""
        start = len(self.names)
        self.names.extend(nm)
        self.theta0.append(np.asarray(v0, float))
        self.lo.append(np.asarray(l, float))
        self.hi.append(np.asarray(h, float))
        self.log.append(np.full(len(nm), lg))
        self.fixed.append(np.full(len(nm), fx))
        self.blocks[block] = slice(start, len(self.names))


def _initial_weights(
    system: System, spec: MPCSpec
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Q0, R0, T0 (positive, searched in log scale) and the |G| bounds."""
    Q0 = system.Q if spec.Q0 is None else np.asarray(spec.Q0, float)
    R0 = system.R if spec.R0 is None else np.asarray(spec.R0, float)
    T0 = Q0 if spec.T0 is None else np.asarray(spec.T0, float)
    if np.any(Q0 <= 0) or np.any(R0 <= 0) or np.any(T0 <= 0):
        raise ValueError("MPC weights Q0, R0, T0 must be positive (they are searched in log scale)")
    if spec.G_bound is None:
        # a linear term that moves the optimum by about one constraint half-width
        G_bound = np.concatenate([2 * Q0 * system.x_scale, 2 * R0 * system.u_scale])
    else:
        G_bound = np.asarray(spec.G_bound, float)
    return Q0, R0, T0, G_bound


def _add_model_block(b: _Blocks, system: System, spec: MPCSpec) -> list[int]:
    """The learnable model parameters ``model_<name>`` around the imperfect model's values
    (log scale where positive); returns their indices in ``system.param_names``."""
    pnames = list(system.param_names)
    idx = []
    for n in spec.learn_model:
        if n not in pnames:
            raise ValueError(f"unknown model parameter '{n}'; known: {pnames}")
        idx.append(pnames.index(n))
    p0 = system.models.get("imperfect", system.true_params)[idx]
    m = spec.model_log_range
    pos = p0 > 0
    lo_m = np.where(pos, p0 * np.exp(-m), p0 - m * np.abs(p0) - 1)
    hi_m = np.where(pos, p0 * np.exp(m), p0 + m * np.abs(p0) + 1)
    b.add("model", [f"model_{n}" for n in spec.learn_model], p0, lo_m, hi_m, False, False)
    b.log[-1] = pos.copy()
    return idx


def _add_backoff_block(b: _Blocks, system: System, spec: MPCSpec) -> None:
    """State-constraint back-offs ``b_lb_<x>``, ``b_ub_<x>`` in [0, backoff_max] (eq. violation)."""
    nx, xs = system.nx, system.state_names
    bmax = (
        0.25 * (system.x_ub - system.x_lb)
        if spec.backoff_max is None
        else np.asarray(spec.backoff_max, float)
    )
    bmax = np.where(np.isfinite(bmax), bmax, 0.0)
    b.add(
        "backoff",
        [f"b_lb_{s}" for s in xs] + [f"b_ub_{s}" for s in xs],
        np.zeros(2 * nx),
        np.zeros(2 * nx),
        np.concatenate([bmax, bmax]),
        False,
        False,
    )
