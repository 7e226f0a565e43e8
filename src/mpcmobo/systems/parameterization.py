"""The learnable parameter vector theta of the MPC (eq. V0 with the cost of section 5)."""

from __future__ import annotations

from collections.abc import Sequence
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
    parameters listed in ``learn_model`` and then those of ``identify`` not among them
    (``model_<name>``; the identified ones are fixed for the learners' search: identification
    sets them) and, if ``learn_backoff``, state constraint back-offs ``b_lb_<x>``,
    ``b_ub_<x>`` (2 nx).

    With ``full_weights``, the blocks ``T``, ``Q`` and ``R`` hold instead the lower-triangular
    Cholesky factor ``L`` of a full weight matrix ``W = L L^T`` (entries ``LT_<a>_<b>``,
    ``LQ_<a>_<b>``, ``LR_<a>_<b>``, row by row): its diagonal is searched in log scale, so ``W``
    stays positive definite everywhere in the search box. ``Q0``, ``R0``, ``T0`` may then be
    positive-definite matrices.
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
    identify: tuple[str, ...] = ()  # model parameters in theta that identification sets
    model_log_range: float = 0.7
    learn_backoff: bool = False
    backoff_max: np.ndarray | None = None  # upper bound of each back-off (nx,)
    full_weights: bool = False  # T, Q, R full positive-definite matrices (Cholesky factors)
    Gamma_h: np.ndarray | None = None  # slack penalties of the path constraints (nh,)

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
        _add_weights(b, "T", xs, T0, r, spec.full_weights)
        G0 = np.zeros(system.nx + system.nu)
        b.add("G", [f"G_{s}" for s in (*xs, *us)], G0, -G_bound, G_bound, False, False)
        _add_weights(b, "Q", xs, Q0, r, spec.full_weights)
        _add_weights(b, "R", us, R0, r, spec.full_weights)
        idx = _add_model_block(b, system, spec) if spec.learn_model or spec.identify else []
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


def _add_weights(
    b: _Blocks, block: str, labels: Sequence[str], W0: np.ndarray, r: float, full: bool
) -> None:
    """A weight block: the diagonal ``W0`` (log scale, theta0 * e^(+-r)) or, ``full``, the
    Cholesky factor of ``W0`` (diagonal in log scale within sqrt(W0_ii) e^(+-r/2), the
    off-diagonal entries within +-sqrt(W0_ii) e^(r/2))."""
    if not full:
        b.add(
            block,
            [f"{block}_{s}" for s in labels],
            W0,
            W0 * np.exp(-r),
            W0 * np.exp(r),
            True,
            False,
        )
        return
    L0 = np.linalg.cholesky(W0 if W0.ndim == 2 else np.diag(W0))
    rows, cols = np.tril_indices(len(labels))
    names = [f"L{block}_{labels[int(i)]}_{labels[int(j)]}" for i, j in zip(rows, cols)]
    d = np.sqrt(np.diag(L0 @ L0.T))[rows]
    diag = rows == cols
    lo = np.where(diag, L0[rows, cols] * np.exp(-r / 2), -d * np.exp(r / 2))
    hi = np.where(diag, L0[rows, cols] * np.exp(r / 2), d * np.exp(r / 2))
    b.add(block, names, L0[rows, cols], lo, hi, False, False)
    b.log[-1] = diag.copy()


def weight_matrix(entries: Any, n: int) -> Any:
    """``W = L L^T`` from the row-by-row lower-triangular entries of ``L`` (CasADi or numpy)."""
    import casadi as ca

    L = ca.SX.zeros(n, n) if isinstance(entries, ca.SX) else np.zeros((n, n))
    k = 0
    for i in range(n):
        for j in range(i + 1):
            L[i, j] = entries[k]
            k += 1
    return ca.mtimes(L, L.T) if isinstance(L, ca.SX) else L @ L.T


def _initial_weights(
    system: System, spec: MPCSpec
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Q0, R0, T0 (positive, searched in log scale; with ``full_weights`` also positive-definite
    matrices) and the |G| bounds."""
    Q0 = system.Q if spec.Q0 is None else np.asarray(spec.Q0, float)
    R0 = system.R if spec.R0 is None else np.asarray(spec.R0, float)
    T0 = Q0 if spec.T0 is None else np.asarray(spec.T0, float)
    for name, W, n in (("Q0", Q0, system.nx), ("R0", R0, system.nu), ("T0", T0, system.nx)):
        if W.ndim == 2 and spec.full_weights:
            if W.shape != (n, n) or not np.allclose(W, W.T):
                raise ValueError(f"mpc_spec.{name} must be a symmetric ({n}, {n}) matrix")
            if np.any(np.linalg.eigvalsh(W) <= 0):
                raise ValueError(f"mpc_spec.{name} must be positive definite")
        elif W.shape != (n,):
            raise ValueError(f"mpc_spec.{name} must have {n} entries, got shape {W.shape}")
        elif np.any(W <= 0):
            raise ValueError(
                f"mpc_spec.{name} must be positive (MPC weights are searched in log scale)"
            )
    Qd = np.diag(Q0) if Q0.ndim == 2 else Q0
    Rd = np.diag(R0) if R0.ndim == 2 else R0
    if spec.G_bound is None:
        # a linear term that moves the optimum by about one constraint half-width
        G_bound = np.concatenate([2 * Qd * system.x_scale, 2 * Rd * system.u_scale])
    else:
        G_bound = np.asarray(spec.G_bound, float)
    return Q0, R0, T0, G_bound


def _add_model_block(b: _Blocks, system: System, spec: MPCSpec) -> list[int]:
    """The model parameters in theta, ``model_<name>``, around the imperfect model's values (log
    scale where positive): the learnable ones, then the identified ones not among them (fixed
    for the search); returns their indices in ``system.param_names``."""
    pnames = list(system.param_names)
    names = [*spec.learn_model, *(n for n in spec.identify if n not in spec.learn_model)]
    idx = []
    for n in names:
        if n not in pnames:
            raise ValueError(f"unknown model parameter '{n}'; known: {pnames}")
        idx.append(pnames.index(n))
    p0 = system.models.get("imperfect", system.true_params)[idx]  # type: ignore[index]  # "imperfect" is required
    m = spec.model_log_range
    pos = p0 > 0
    lo_m = np.where(pos, p0 * np.exp(-m), p0 - m * np.abs(p0) - 1)
    hi_m = np.where(pos, p0 * np.exp(m), p0 + m * np.abs(p0) + 1)
    fixed = np.array([n not in spec.learn_model for n in names])
    b.add("model", [f"model_{n}" for n in names], p0, lo_m, hi_m, False, fixed)
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
