"""The search space of the learnable MPC parameters theta."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike


@dataclass(frozen=True)
class SearchSpace:
    """Box bounds on theta, per coordinate linear or logarithmic, some coordinates fixed.

    Learners search the unit cube ``[0, 1]^d`` of the ``d`` free coordinates. For a log-scaled
    coordinate ``z = (log theta - log lo) / (log hi - log lo)``, for a linear one
    ``z = (theta - lo) / (hi - lo)``. Fixed coordinates keep the value of the base vector that
    :meth:`from_unit` is given (the learners give their theta0): the constant ``theta_c`` of
    the CSTR cost, for instance, changes ``V_theta`` but never the policy, so searching it
    wastes evaluations.
    """

    names: tuple[str, ...]
    lower: np.ndarray
    upper: np.ndarray
    log: np.ndarray
    fixed: np.ndarray

    def __init__(
        self,
        names: Sequence[str],
        lower: ArrayLike,
        upper: ArrayLike,
        log: ArrayLike | None = None,
        fixed: ArrayLike | None = None,
    ) -> None:
        n = len(names)
        lower = np.asarray(lower, dtype=float).reshape(-1)
        upper = np.asarray(upper, dtype=float).reshape(-1)
        log = np.zeros(n, bool) if log is None else np.asarray(log, dtype=bool).reshape(-1)
        fixed = np.zeros(n, bool) if fixed is None else np.asarray(fixed, dtype=bool).reshape(-1)
        for label, arr in (("lower", lower), ("upper", upper), ("log", log), ("fixed", fixed)):
            if arr.shape != (n,):
                raise ValueError(
                    f"search space: '{label}' has {arr.shape[0]} entries, expected {n}"
                )
        if not (np.all(np.isfinite(lower)) and np.all(np.isfinite(upper))):
            raise ValueError("search space: bounds must be finite")
        bad = np.flatnonzero(~(lower <= upper))
        if bad.size:
            raise ValueError(f"search space: lower > upper for {[names[i] for i in bad.tolist()]}")
        badlog = np.flatnonzero(log & (lower <= 0))
        if badlog.size:
            raise ValueError(
                f"search space: log-scaled parameters need positive bounds: "
                f"{[names[i] for i in badlog.tolist()]}"
            )
        free_deg = np.flatnonzero(~fixed & (lower == upper))
        fixed = fixed.copy()
        fixed[free_deg] = True  # a zero-width interval is not searchable
        object.__setattr__(self, "names", tuple(names))
        object.__setattr__(self, "lower", lower)
        object.__setattr__(self, "upper", upper)
        object.__setattr__(self, "log", log)
        object.__setattr__(self, "fixed", fixed)

    @property
    def n_theta(self) -> int:
        """Number of coordinates of theta."""
        return len(self.names)

    @property
    def free(self) -> np.ndarray:
        """Boolean mask of the searched (not fixed) coordinates."""
        return ~self.fixed

    @property
    def dim(self) -> int:
        """Number of searched (free) coordinates."""
        return int(np.count_nonzero(self.free))

    @property
    def free_names(self) -> list[str]:
        """Names of the searched (free) coordinates."""
        return [n for n, f in zip(self.names, self.free) if f]

    def _check(self, theta: np.ndarray) -> np.ndarray:
        theta = np.asarray(theta, dtype=float).reshape(-1)
        if theta.shape != (self.n_theta,):
            raise ValueError(f"theta has {theta.shape[0]} entries, expected {self.n_theta}")
        return theta

    def clip(self, theta: np.ndarray) -> np.ndarray:
        """``theta`` clipped to the bounds."""
        return np.clip(self._check(theta), self.lower, self.upper)

    def contains(self, theta: np.ndarray, tol: float = 1e-12) -> bool:
        """Whether ``theta`` lies within the bounds (up to ``tol`` times the span)."""
        theta = self._check(theta)
        span = np.maximum(self.upper - self.lower, 1.0)
        return bool(
            np.all(theta >= self.lower - tol * span) and np.all(theta <= self.upper + tol * span)
        )

    def _warp(
        self, v: np.ndarray, lo: np.ndarray, hi: np.ndarray, log: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        v, lo, hi = v.copy(), lo.copy(), hi.copy()
        v[..., log] = np.log(np.maximum(v[..., log], 1e-300))
        lo[log], hi[log] = np.log(lo[log]), np.log(hi[log])
        return v, lo, hi

    def to_unit(self, theta: np.ndarray) -> np.ndarray:
        """Map full theta(s) ``(..., n_theta)`` to the unit cube of the free coordinates."""
        theta = np.asarray(theta, dtype=float)
        if theta.shape[-1] != self.n_theta:
            raise ValueError(f"theta has {theta.shape[-1]} entries, expected {self.n_theta}")
        f = self.free
        v, lo, hi = self._warp(theta[..., f], self.lower[f], self.upper[f], self.log[f])
        return np.clip((v - lo) / (hi - lo), 0.0, 1.0)

    def from_unit(self, z: np.ndarray, base: np.ndarray) -> np.ndarray:
        """Map unit-cube point(s) ``(..., dim)`` back to full theta, fixed entries from ``base``."""
        z = np.clip(np.asarray(z, dtype=float), 0.0, 1.0)
        if z.shape[-1] != self.dim:
            raise ValueError(f"unit point has {z.shape[-1]} entries, expected {self.dim}")
        f = self.free
        lo, hi, lg = self.lower[f], self.upper[f], self.log[f]
        llo, lhi = lo.copy(), hi.copy()
        llo[lg], lhi[lg] = np.log(lo[lg]), np.log(hi[lg])
        v = llo + z * (lhi - llo)
        v[..., lg] = np.exp(v[..., lg])
        out = np.broadcast_to(self._check(base), z.shape[:-1] + (self.n_theta,)).copy()
        out[..., f] = v
        return np.clip(out, self.lower, self.upper)

    def dtheta_dz(self, theta: np.ndarray) -> np.ndarray:
        """Jacobian (diagonal) of ``from_unit`` at ``theta``, free coordinates only.

        ``dtheta/dz = hi - lo`` for a linear coordinate and ``theta (log hi - log lo)`` for a
        log one: the chain rule that turns a gradient in theta into one in the unit cube.
        """
        theta = self._check(theta)
        f = self.free
        lo, hi, lg = self.lower[f], self.upper[f], self.log[f]
        out = hi - lo
        out[lg] = theta[f][lg] * (np.log(hi[lg]) - np.log(lo[lg]))
        return out

    def to_dict(self) -> dict:
        """The space as a plain dictionary."""
        return {
            "names": list(self.names),
            "lower": self.lower.tolist(),
            "upper": self.upper.tolist(),
            "log": self.log.tolist(),
            "fixed": self.fixed.tolist(),
        }
