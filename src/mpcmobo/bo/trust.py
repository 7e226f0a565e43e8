"""A trust region of the unit cube that travels with the deployed theta (TuRBO-style).

After Eriksson et al. (2019), "Scalable global optimization via local Bayesian optimization"
(TuRBO-1): the acquisition is maximised only inside a box of side ``L`` of the unit cube,
centred at a point (here the learner's deployed theta, theta0 at first); ``L`` doubles after
``success_tolerance`` successes in a row and halves after ``failure_tolerance`` failures in a
row, capped at ``length_max``. What differs from TuRBO-1, and why:

* the centre is the deployed theta (the learner's incumbent rule), not the best noisy
  observation: a single episode is too noisy to be the centre (``docs/benchmarks.md``);
* one GP on all the data, not a local GP: the per-start offsets need every episode;
* when ``L`` falls below ``length_min`` the region restarts at ``length_init`` around the same
  deployed theta (the data are kept), instead of a fresh design elsewhere: the deployed theta
  must stay the one the evidence supports;
* the box is a cube (no lengthscale weighting): with a few dozen noisy episodes the fitted
  lengthscales are not yet trustworthy.

All lengths are in the unit cube of the search space, so the defaults are scale-free: the
same fraction of every declared range on any system.

:class:`TrustRegion` is the configuration (frozen); :class:`TrustState` what is learned (the
current length and the two counters), saved in the learner's state.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

__all__ = ["TrustRegion", "TrustState"]


@dataclass(frozen=True)
class TrustRegion:
    """Options of the trust region (all lengths: side of the box in the unit cube).

    ``failure_tolerance = 0`` means ``max(4, d)`` failures (TuRBO-1's rule for one point per
    batch, ``d`` the number of searched coordinates).
    """

    length_init: float = 0.2
    length_min: float = 0.0125
    length_max: float = 1.6
    success_tolerance: int = 2
    failure_tolerance: int = 0

    def __post_init__(self) -> None:
        for name in ("length_init", "length_min", "length_max"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not np.isfinite(v):
                raise ValueError(f"trust_region.{name} must be a finite number, got {v!r}")
        if not 0 < self.length_min <= self.length_init <= self.length_max <= 2:
            raise ValueError(
                "trust_region needs 0 < length_min <= length_init <= length_max <= 2 (unit "
                f"cube), got length_min {self.length_min}, length_init {self.length_init}, "
                f"length_max {self.length_max}"
            )
        for name, low in (("success_tolerance", 1), ("failure_tolerance", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ValueError(f"trust_region.{name} must be an integer >= {low}, got {v!r}")

    def failures(self, d: int) -> int:
        """Failures in a row that halve the length (``max(4, d)`` when left at 0)."""
        return self.failure_tolerance if self.failure_tolerance > 0 else max(4, int(d))

    def box(self, center: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper corners of the box of side ``length`` centred at ``center``,
        clipped to the unit cube."""
        c = np.asarray(center, dtype=float)
        return np.clip(c - length / 2, 0.0, 1.0), np.clip(c + length / 2, 0.0, 1.0)

    def start(self) -> TrustState:
        """The state before any episode: ``length_init``, no success, no failure."""
        return TrustState(float(self.length_init), 0, 0)

    def update(self, state: TrustState, success: bool, d: int) -> TrustState:
        """The state after one more proposal judged a ``success`` (or not)."""
        length, s, f = state.length, state.successes, state.failures
        if success:
            s, f = s + 1, 0
        else:
            s, f = 0, f + 1
        if s >= self.success_tolerance:
            length, s = min(self.length_max, 2.0 * length), 0
        elif f >= self.failures(d):
            length, f = length / 2.0, 0
            if length < self.length_min:
                length = float(self.length_init)  # restart around the same deployed theta
        return TrustState(float(length), s, f)


@dataclass(frozen=True)
class TrustState:
    """The current side length of the box and the successes / failures in a row."""

    length: float
    successes: int
    failures: int

    def to_dict(self) -> dict[str, Any]:
        """As plain Python (for a learner's ``state_dict``)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> TrustState:
        """The inverse of :meth:`to_dict`."""
        return cls(float(d["length"]), int(d["successes"]), int(d["failures"]))
