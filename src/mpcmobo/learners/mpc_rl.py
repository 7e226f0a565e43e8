"""MPC-RL: compatible deterministic policy gradient steps on theta (eq. theta)."""

from __future__ import annotations

import numpy as np

from mpcmobo.learners.base import EpisodeResult, Learner
from mpcmobo.systems.space import SearchSpace


class MPCRL(Learner):
    """``theta <- theta - alpha grad_theta J`` (eq. theta), projected onto the search bounds.

    The CDPG gradient (eq. DPG) is taken with respect to theta; the step is made in the
    normalised coordinates ``z`` of the search space (log coordinates for the weights), where
    ``grad_z J = grad_theta J * d theta / d z``, so that one learning rate suits weights of 10 and
    of 5000 alike. ``optimizer="adam"`` (default) rescales each coordinate by its running RMS;
    ``"sgd"`` is the plain rule with the gradient norm clipped to ``max_step / alpha``.
    ``lr_decay = c > 0`` makes the step size ``alpha / (1 + c t)`` after ``t`` steps (a
    Robbins-Monro schedule; 0, the default, is the paper's constant step).
    Episodes whose critic failed (or whose objectives are NaN) make no step.
    """

    name = "mpc-rl"

    def __init__(
        self,
        space: SearchSpace,
        theta0: np.ndarray,
        seed: int = 0,
        *,
        lr: float = 0.03,
        optimizer: str = "adam",
        beta1: float = 0.9,
        beta2: float = 0.999,
        eps: float = 1e-8,
        max_step: float = 0.1,
        lr_decay: float = 0.0,
    ) -> None:
        super().__init__(space, theta0, seed)
        if optimizer not in ("adam", "sgd"):
            raise ValueError(f"optimizer must be 'adam' or 'sgd', got '{optimizer}'")
        if lr <= 0:
            raise ValueError(f"learning rate must be positive, got {lr}")
        if not lr_decay >= 0:
            raise ValueError(f"lr_decay must be >= 0, got {lr_decay}")
        self.lr, self.optimizer, self.lr_decay = float(lr), optimizer, float(lr_decay)
        self.beta1, self.beta2, self.eps, self.max_step = beta1, beta2, eps, max_step
        self.z = space.to_unit(self.theta0)
        self.m = np.zeros(space.dim)
        self.v = np.zeros(space.dim)
        self.t = 0

    def _theta(self) -> np.ndarray:
        return self.space.from_unit(self.z, base=self.theta0)

    def propose(self) -> np.ndarray:
        return self._theta()

    def incumbent(self) -> np.ndarray:
        return self._theta()

    def observe(self, theta: np.ndarray, result: EpisodeResult) -> None:
        self.n_observed += 1
        g = np.asarray(result.grad, dtype=float)
        if not result.critic_ok or not np.all(np.isfinite(g)) or not result.valid:
            return
        theta = self.space.clip(theta)
        gz = g[self.space.free] * self.space.dtheta_dz(theta)
        lr = self.lr / (1.0 + self.lr_decay * self.t)
        if self.optimizer == "adam":
            self.t += 1
            self.m = self.beta1 * self.m + (1 - self.beta1) * gz
            self.v = self.beta2 * self.v + (1 - self.beta2) * gz**2
            mh = self.m / (1 - self.beta1**self.t)
            vh = self.v / (1 - self.beta2**self.t)
            step = lr * mh / (np.sqrt(vh) + self.eps)
        else:
            self.t += 1
            step = lr * gz
        norm = np.linalg.norm(step)
        if norm > self.max_step:
            step *= self.max_step / norm
        self.z = np.clip(self.z - step, 0.0, 1.0)  # projection onto the bounds

    def state_dict(self) -> dict:
        d = super().state_dict()
        d.update({"z": self.z.copy(), "m": self.m.copy(), "v": self.v.copy(), "t": self.t})
        return d

    def load_state_dict(self, state: dict) -> None:
        super().load_state_dict(state)
        self.z, self.m, self.v = (np.array(state[k], dtype=float) for k in ("z", "m", "v"))
        self.t = int(state["t"])
