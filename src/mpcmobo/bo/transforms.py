"""Cost-space transforms: costs to be minimised <-> the GP's maximised targets (eq. GP).

The GPs model ``t = -g(y)``: ``g`` is the identity, or for costs spanning orders of magnitude
(e.g. the CSTR's f1) a shifted log, and the sign flip turns minimisation into BoTorch's
maximisation. Each step is a small object, chained like BoTorch's ``ChainedOutcomeTransform``:

* ``fit(Y)`` learns what the step needs from the finite costs ``Y`` (n, m) of a GP fit;
* ``forward(Y)`` maps values to the model space;
* ``untransform(mean, std)`` maps a Gaussian posterior's mean and std (n, m) back (eq.
  mean_var in cost units).

Shifted log: ``g(y) = log(y + c)`` with the offset ``c`` recomputed on each fit from the data:
``c = 0`` if ``min y > 0`` (plain ``log y``); otherwise ``c = -min y + 0.01 (max y - min y)``
(or ``+1e-6`` if the range is zero), so the smallest cost maps to ``log(1% of the range)``
rather than to ``-inf`` (the objectives f3, f4 are exactly 0 for many episodes). The posterior
of ``g(y)`` is ``N(m, s^2)``, so ``y + c`` is log-normal: its mean and standard deviation are
``E[y] = exp(m + s^2/2) - c``, ``Std[y] = exp(m + s^2/2) sqrt(exp(s^2) - 1)``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import numpy as np

__all__ = ["ChainedTransform", "Negate", "ShiftedLog", "cost_transform"]


class ShiftedLog:
    """``log(y + c)`` on the outputs flagged in ``flags``, identity on the others."""

    def __init__(self, flags: Sequence[bool]) -> None:
        self.flags = [bool(b) for b in flags]
        self.offsets_ = np.zeros(len(self.flags))  # c per output, set by fit

    def fit(self, Y: np.ndarray) -> ShiftedLog:
        """Choose the offsets ``c`` so that ``y + c > 0`` on the flagged outputs of ``Y``; returns
        self."""
        c = np.zeros(len(self.flags))
        for j in np.flatnonzero(self.flags):
            lo, hi = Y[:, j].min(), Y[:, j].max()
            if lo <= 0:
                c[j] = -lo + (0.01 * (hi - lo) if hi > lo else 1e-6)
        self.offsets_ = c
        return self

    def forward(self, Y: np.ndarray) -> np.ndarray:
        """``log(y + c)``, clamped at ``y + c >= 1e-300`` (only matters for values below the
        fitted data, e.g. a reference point)."""
        Y = Y.copy()
        for j in np.flatnonzero(self.flags):
            Y[:, j] = np.log(np.maximum(Y[:, j] + self.offsets_[j], 1e-300))
        return Y

    def untransform(self, mean: np.ndarray, std: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean and std of the log-normal ``y`` (module docstring) on the flagged outputs."""
        mean, std = mean.copy(), std.copy()
        for j in np.flatnonzero(self.flags):
            s2 = std[:, j] ** 2
            scale = np.exp(mean[:, j] + 0.5 * s2)
            mean[:, j] = scale - self.offsets_[j]
            std[:, j] = scale * np.sqrt(np.expm1(s2))
        return mean, std


class Negate:
    """``-y``: costs (minimised) as BoTorch's maximised targets."""

    def fit(self, Y: np.ndarray) -> Negate:
        """Nothing to fit; returns self."""
        return self

    def forward(self, Y: np.ndarray) -> np.ndarray:
        """``-Y``."""
        return -Y

    def untransform(self, mean: np.ndarray, std: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean and std of ``y`` from those of ``-y``."""
        return -mean, std.copy()


class ChainedTransform:
    """The steps applied in order by ``forward``, undone in reverse order by ``untransform``."""

    def __init__(self, *steps: Any) -> None:
        self.steps = steps

    def fit(self, Y: np.ndarray) -> ChainedTransform:
        """Fit every step on the output of the steps before it; returns self."""
        for step in self.steps:
            Y = step.fit(Y).forward(Y)
        return self

    def forward(self, Y: np.ndarray) -> np.ndarray:
        """The steps applied in order."""
        for step in self.steps:
            Y = step.forward(Y)
        return Y

    def untransform(self, mean: np.ndarray, std: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Mean and std in the original space: the steps undone in reverse order."""
        for step in reversed(self.steps):
            mean, std = step.untransform(mean, std)
        return mean, std


def cost_transform(log_outcomes: Sequence[bool]) -> ChainedTransform:
    """``t = -g(y)``: the shifted log on the flagged outputs, then the sign flip."""
    return ChainedTransform(ShiftedLog(log_outcomes), Negate())
