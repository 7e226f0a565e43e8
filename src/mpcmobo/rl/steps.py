"""Step rules of MPC-RL (eq. theta): ``theta <- theta - step(grad_theta J)``.

Each rule is a small class around its update: it takes the gradient of one episode and returns
the step to subtract, in the coordinates it declares (``coordinates``): ``"unit"``, the
normalised coordinates ``z`` of the search space (the learner converts the gradient with
``d theta / d z``), or ``"theta"``, theta itself. Its state (moments, step count) is plain
NumPy, saved and restored by the learner.

| rule | step | option |
|---|---|---|
| :class:`Adam` | ``lr * m_hat / (sqrt(v_hat) + eps)``, norm clipped to ``max_step`` | ``optimizer = "adam"`` |
| :class:`PlainGradient` | ``lr * g`` in theta, no clipping (the paper's eq. theta) | ``optimizer = "gd"`` |
"""

from __future__ import annotations

import numpy as np

__all__ = ["Adam", "PlainGradient", "StepRule"]


class StepRule:
    """Base class: ``step(g) -> delta`` (subtract it), with its state in ``m, v, t``."""

    name = "rule"
    coordinates = "unit"

    def __init__(self, lr: float) -> None:
        if not lr > 0 or not np.isfinite(lr):
            raise ValueError(f"learning rate must be positive, got {lr}")
        self.lr = float(lr)
        self.m = np.zeros(0)
        self.v = np.zeros(0)
        self.t = 0

    def step(self, g: np.ndarray) -> np.ndarray:
        """The step to subtract for the gradient ``g`` (advances the rule's state)."""
        raise NotImplementedError

    def state_dict(self) -> dict:
        """The rule's state: moments ``m``, ``v`` and step count ``t``."""
        return {"m": self.m.copy(), "v": self.v.copy(), "t": self.t}

    def load_state_dict(self, state: dict) -> None:
        """Continue from a :meth:`state_dict`."""
        self.m, self.v = (np.array(state[k], dtype=float) for k in ("m", "v"))
        self.t = int(state["t"])


class Adam(StepRule):
    """Adam (Kingma and Ba): each coordinate scaled by its running RMS; the step's norm
    clipped to ``max_step``."""

    name = "adam"

    def __init__(
        self,
        lr: float = 0.03,
        beta1: float = 0.9,
        beta2: float = 0.999,
        eps: float = 1e-8,
        max_step: float = 0.1,
    ) -> None:
        super().__init__(lr)
        if not max_step > 0:
            raise ValueError(f"max_step must be positive, got {max_step}")
        self.beta1, self.beta2, self.eps = float(beta1), float(beta2), float(eps)
        self.max_step = float(max_step)

    def step(self, g: np.ndarray) -> np.ndarray:
        """See :meth:`StepRule.step`."""
        if self.m.shape != g.shape:
            self.m, self.v = np.zeros_like(g), np.zeros_like(g)
        self.t += 1
        self.m = self.beta1 * self.m + (1 - self.beta1) * g
        self.v = self.beta2 * self.v + (1 - self.beta2) * g**2
        mh = self.m / (1 - self.beta1**self.t)
        vh = self.v / (1 - self.beta2**self.t)
        step = self.lr * mh / (np.sqrt(vh) + self.eps)
        norm = np.linalg.norm(step)
        return step * (self.max_step / norm) if norm > self.max_step else step


class PlainGradient(StepRule):
    """The paper's rule (eq. theta): ``theta <- theta - alpha grad_theta J`` in theta's own
    coordinates, constant ``alpha``, no clipping. The learner projects the result onto the
    search bounds."""

    name = "gd"
    coordinates = "theta"

    def step(self, g: np.ndarray) -> np.ndarray:
        """See :meth:`StepRule.step`."""
        self.t += 1
        return self.lr * g
