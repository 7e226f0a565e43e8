"""Step rules of MPC-RL (eq. theta): ``theta <- theta - step(grad_theta J)``.

Each rule is a small class around its update: it takes the gradient of one episode and returns
the step to subtract, in the coordinates it declares (``coordinates``): ``"unit"``, the
normalised coordinates ``z`` of the search space (the learner converts the gradient with
``d theta / d z``), or ``"theta"``, theta itself. Its state (moments, step count) is plain
NumPy, saved and restored by the learner. ``lr_decay = c`` makes the learning rate
``lr / (1 + c t)`` after ``t`` steps (a Robbins-Monro schedule; 0: constant).

| rule | step | chosen by |
|---|---|---|
| :class:`Adam` | ``lr * m_hat / (sqrt(v_hat) + eps)``, norm clipped to ``max_step`` | ``optimizer = "adam"`` |
| :class:`SGD` | ``lr * g``, norm clipped to ``max_step`` | ``optimizer = "sgd"`` |
| :class:`PlainGradient` | ``lr * g`` in theta, no clipping (the paper's eq. theta) | ``optimizer = "gd"`` |
| :class:`TrustStep` | ``radius * m_hat``, ``m`` the running mean of unit gradient directions | ``optimizer = "trust"`` |

:class:`TrustStep` is scale-free twice: the step is a length in the unit cube of the search
space (so it does not depend on the units of theta), and it uses only the direction of the
gradient (so it does not depend on the units of the cost). The running mean of unit directions
has length about 1 when successive gradients agree and about ``sqrt((1 - beta1) / (1 + beta1))``
when they are noise, so the step shrinks by itself where the gradient is noise.
"""

from __future__ import annotations

import numpy as np


class StepRule:
    """Base class: ``step(g) -> delta`` (subtract it), with its state in ``m, v, t``."""

    name = "rule"
    coordinates = "unit"

    def __init__(self, lr: float, lr_decay: float = 0.0, max_step: float | None = None) -> None:
        if not lr > 0 or not np.isfinite(lr):
            raise ValueError(f"learning rate must be positive, got {lr}")
        if not lr_decay >= 0:
            raise ValueError(f"lr_decay must be >= 0, got {lr_decay}")
        if max_step is not None and not max_step > 0:
            raise ValueError(f"max_step must be positive, got {max_step}")
        self.lr, self.lr_decay, self.max_step = float(lr), float(lr_decay), max_step
        self.m = np.zeros(0)
        self.v = np.zeros(0)
        self.t = 0

    def rate(self) -> float:
        """The learning rate of the next step (``t`` steps made so far)."""
        return self.lr / (1.0 + self.lr_decay * self.t)

    def _clip(self, step: np.ndarray) -> np.ndarray:
        norm = np.linalg.norm(step)
        if self.max_step is not None and norm > self.max_step:
            step = step * (self.max_step / norm)
        return step

    def _moments(self, g: np.ndarray) -> None:
        if self.m.shape != g.shape:
            self.m, self.v = np.zeros_like(g), np.zeros_like(g)

    def step(self, g: np.ndarray) -> np.ndarray:
        """The step to subtract for the gradient ``g`` (advances the rule's state)."""
        raise NotImplementedError

    def state_dict(self) -> dict:
        """The rule's state: moments ``m``, ``v`` and step count ``t`` (old checkpoint keys)."""
        return {"m": self.m.copy(), "v": self.v.copy(), "t": self.t}

    def load_state_dict(self, state: dict) -> None:
        """Continue from a :meth:`state_dict`."""
        self.m, self.v = (np.array(state[k], dtype=float) for k in ("m", "v"))
        self.t = int(state["t"])


class Adam(StepRule):
    """Adam (Kingma and Ba): each coordinate scaled by its running RMS; norm clipped."""

    name = "adam"

    def __init__(
        self,
        lr: float = 0.03,
        beta1: float = 0.9,
        beta2: float = 0.999,
        eps: float = 1e-8,
        max_step: float | None = 0.1,
        lr_decay: float = 0.0,
    ) -> None:
        super().__init__(lr, lr_decay, max_step)
        self.beta1, self.beta2, self.eps = float(beta1), float(beta2), float(eps)

    def step(self, g: np.ndarray) -> np.ndarray:
        """See :meth:`StepRule.step`."""
        self._moments(g)
        lr = self.rate()
        self.t += 1
        self.m = self.beta1 * self.m + (1 - self.beta1) * g
        self.v = self.beta2 * self.v + (1 - self.beta2) * g**2
        mh = self.m / (1 - self.beta1**self.t)
        vh = self.v / (1 - self.beta2**self.t)
        return self._clip(lr * mh / (np.sqrt(vh) + self.eps))


class SGD(StepRule):
    """``lr * g`` in the unit coordinates, norm clipped to ``max_step``."""

    name = "sgd"

    def __init__(self, lr: float = 0.03, max_step: float | None = 0.1, lr_decay: float = 0.0):
        super().__init__(lr, lr_decay, max_step)

    def step(self, g: np.ndarray) -> np.ndarray:
        """See :meth:`StepRule.step`."""
        lr = self.rate()
        self.t += 1
        return self._clip(lr * g)


class PlainGradient(StepRule):
    """The paper's rule (eq. theta): ``theta <- theta - alpha grad_theta J`` in theta's own
    coordinates, constant ``alpha`` (unless ``lr_decay``), no clipping. The learner projects
    the result onto the search bounds."""

    name = "gd"
    coordinates = "theta"

    def __init__(self, lr: float = 0.03, lr_decay: float = 0.0) -> None:
        super().__init__(lr, lr_decay, None)

    def step(self, g: np.ndarray) -> np.ndarray:
        """See :meth:`StepRule.step`."""
        lr = self.rate()
        self.t += 1
        return lr * g


class TrustStep(StepRule):
    """A step of length ``lr * |m_hat|`` (``lr``: the trust radius, a length in the unit cube)
    along ``m_hat``, the bias-corrected running mean (``beta1``) of the unit directions
    ``g / |g|``. See the module docstring."""

    name = "trust"

    def __init__(self, lr: float = 0.05, beta1: float = 0.9, lr_decay: float = 0.0) -> None:
        super().__init__(lr, lr_decay, None)
        if not 0 <= beta1 < 1:
            raise ValueError(f"beta1 must be in [0, 1), got {beta1}")
        self.beta1 = float(beta1)

    def step(self, g: np.ndarray) -> np.ndarray:
        """See :meth:`StepRule.step`."""
        self._moments(g)
        norm = np.linalg.norm(g)
        if norm == 0:
            return np.zeros_like(g)
        lr = self.rate()
        self.t += 1
        self.m = self.beta1 * self.m + (1 - self.beta1) * g / norm
        return lr * self.m / (1 - self.beta1**self.t)


STEP_RULES: dict[str, type[StepRule]] = {
    cls.name: cls for cls in (Adam, SGD, PlainGradient, TrustStep)
}
