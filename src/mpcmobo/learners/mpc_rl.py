"""MPC-RL: compatible deterministic policy gradient steps on theta (eq. theta)."""

from __future__ import annotations

import numpy as np

from mpcmobo.bo.context import ContextSpec
from mpcmobo.learners.base import EpisodeResult, Learner
from mpcmobo.learners.deploy import DeployRule
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

    ``deploy_confidence = p`` (issue 11): the learner keeps stepping from its iterate but
    deploys (``incumbent()``) its best verified theta: a GP on log f1 of its own episodes, over
    ``(z, c)`` with ``context = "x0"`` (c the scaled initial state), judges the iterates by
    their expected f1 over a fixed sample of initial states, and the deployed theta changes
    only when a run theta is better with probability at least ``p``
    (:class:`~mpcmobo.learners.deploy.DeployRule`). None (default): the iterate is deployed.
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
        deploy_confidence: float | None = None,
        context: str = "none",
        n_contexts: int = 16,
        incumbent_kappa: float = 0.0,
        contexts: ContextSpec | None = None,
    ) -> None:
        super().__init__(space, theta0, seed)
        if context not in ("none", "x0"):
            raise ValueError(f"context must be 'none' or 'x0', got {context!r}")
        if context == "x0" and contexts is None:
            raise ValueError("context = 'x0' needs the system's contexts (ContextSpec)")
        self.context_spec = contexts
        self.contexts = contexts.sample(int(n_contexts)) if context == "x0" else np.zeros((1, 0))  # type: ignore[union-attr]  # checked above
        self.deploy_rule = (
            None
            if deploy_confidence is None
            else DeployRule(
                kappa=float(incumbent_kappa), deploy_confidence=float(deploy_confidence)
            )
        )
        self._init_judge()
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
        """The current theta of the gradient steps."""
        return self._theta()

    def incumbent(self) -> np.ndarray:
        """The deployed theta: the current one, or with a deploy rule the best verified one."""
        if self.deploy_rule is None:
            return self._theta()
        if np.array_equal(self.deployed_z_, self.space.to_unit(self.theta0)):
            return self.theta0.copy()  # exactly theta0, not its round trip through z
        return self.space.from_unit(self.deployed_z_, base=self.theta0)

    # ------------------------------------------------------------ deployment (issue 11)
    def _init_judge(self) -> None:
        from mpcmobo.bo import GPSurrogate

        dc = self.contexts.shape[1]
        self.judge = None if self.deploy_rule is None else GPSurrogate(1, log_outcomes=(True,))
        self.X_ = np.zeros((0, self.space.dim + dc))  # (z, c) of the learner's own episodes
        self.F_ = np.zeros(0)  # their f1
        self.deployed_z_ = self.space.to_unit(self.theta0)
        self._judge_pre_fit: dict | None = None
        self._deployed_pre_fit = self.deployed_z_.copy()

    def _observe_deploy(self, theta: np.ndarray, result: EpisodeResult) -> None:
        dc = self.contexts.shape[1]
        c = np.zeros(0) if dc == 0 else self.context_spec.unit(result.x0)  # type: ignore[union-attr,arg-type]  # dc > 0: context x0
        x = np.concatenate([self.space.to_unit(self.space.clip(theta)), c])
        self.X_ = np.vstack([self.X_, x])
        self.F_ = np.append(self.F_, result.f1)
        self._judge_fit()

    def _judge_fit(self) -> None:
        self._judge_pre_fit = self.judge.state_dict()  # type: ignore[union-attr]  # with deploy_rule
        self._deployed_pre_fit = self.deployed_z_.copy()
        ok = np.isfinite(self.F_)
        if np.count_nonzero(ok) < 2:
            return
        self.judge.fit(self.X_, self.F_[:, None])  # type: ignore[union-attr]  # with deploy_rule
        d = self.space.dim
        self.deployed_z_ = self.deploy_rule.choose(  # type: ignore[union-attr]  # with the judge
            self.judge,  # type: ignore[arg-type]
            self.X_[ok, :d],
            self.deployed_z_,
            self.contexts,
            None,
            seed=1234 + len(self.F_),
        )

    def observe(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """One gradient step (``optimizer``: Adam or plain) along the episode's CDPG gradient (eq.
        DPG, eq. theta) in normalised coordinates; an episode without a valid gradient is
        skipped."""
        self.n_observed += 1
        if self.deploy_rule is not None:
            self._observe_deploy(theta, result)
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
        """The base state plus the Adam state (z, m, v, t) and the deploy rule's state."""
        d = super().state_dict()
        d.update({"z": self.z.copy(), "m": self.m.copy(), "v": self.v.copy(), "t": self.t})
        if self.deploy_rule is not None:
            d.update(
                {
                    "judge_X": self.X_.copy(),
                    "judge_F": self.F_.copy(),
                    "judge_pre_fit": self._judge_pre_fit,
                    "deployed_pre_fit": self._deployed_pre_fit.copy(),
                }
            )
        return d

    def load_state_dict(self, state: dict) -> None:
        """Continue from a :meth:`state_dict`."""
        super().load_state_dict(state)
        self.z, self.m, self.v = (np.array(state[k], dtype=float) for k in ("z", "m", "v"))
        self.t = int(state["t"])
        if self.deploy_rule is not None:
            self._init_judge()
            if "judge_X" in state:  # else a checkpoint without deployment: start afresh
                self.X_ = np.array(state["judge_X"], float)
                self.F_ = np.array(state["judge_F"], float)
                self.deployed_z_ = np.array(state["deployed_pre_fit"], float)
                if state["judge_pre_fit"] is not None:
                    self.judge.load_state_dict(state["judge_pre_fit"])  # type: ignore[union-attr]
                    self._judge_fit()
