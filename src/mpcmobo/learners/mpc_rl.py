"""MPC-RL: compatible deterministic policy gradient steps on theta (eq. theta)."""

from __future__ import annotations

from typing import Any

import numpy as np

from mpcmobo.bo.context import ContextSpec
from mpcmobo.learners.base import EpisodeResult, Learner, check_choice
from mpcmobo.learners.deploy import (
    ADJUST_MODES,
    DeployRule,
    adjusted_confidence,
    paired_confidence,
    unpaired_confidence,
)
from mpcmobo.rl.judge import PooledJudge, check_confidence
from mpcmobo.rl.steps import STEP_RULES, StepRule
from mpcmobo.systems.space import SearchSpace

DEPLOY_MODES = ("iterate", "pooled", "gp", "verified")
DEPLOY_METRICS = ("stage_cost", "f1")  # what the verified blocks compare
POOLED_CONFIDENCE = 0.99  # default deploy_confidence of the pooled judge
VERIFIED_CONFIDENCE = 0.9  # default deploy_confidence of the verified blocks (as bo and mobo)


class MPCRL(Learner):
    """``theta <- theta - alpha grad_theta J`` (eq. theta), projected onto the search bounds.

    The CDPG gradient (eq. DPG) is taken with respect to theta. The step rule
    (:mod:`mpcmobo.rl.steps`) is chosen by ``optimizer``:

    * ``"adam"`` (default; ``lr`` 0.03, step norm clipped to ``max_step``) and ``"sgd"``
      (``lr * grad``, clipped), both in the normalised coordinates ``z`` of the search space
      (log coordinates for the weights), ``grad_z J = grad_theta J d theta / d z``: Adam's
      per-coordinate RMS scaling makes it free of the units of the cost, the unit cube of the
      units of theta;
    * ``"trust"``: a step of length at most ``lr`` in the unit cube along the
      running mean of the unit gradient directions (scale-free too, and shorter where the
      gradient is noise);
    * ``"gd"``: the paper's plain constant step ``theta <- theta - lr grad_theta J`` in theta
      itself, no clipping (issue 15's paper configuration).

    ``lr`` (default 0.03) is the step size of every rule. ``lr_decay = c > 0`` makes the step size
    ``alpha / (1 + c t)`` after ``t`` steps (0, the default: a constant step). Episodes whose
    critic failed (or whose objectives are NaN) make no step.

    Deployment (issue 11): the learner keeps stepping from its iterate, and ``deploy`` says
    which theta it deploys (``incumbent()``, what J_eval measures):

    * ``"verified"`` (default since session 12): verification blocks. The first
      ``deploy_min_runs`` (6) episodes run theta0 itself; then, every ``deploy_every`` (12)
      gradient steps, the iterate is frozen for a block of ``deploy_min_runs`` episodes run
      **without exploration noise** (``explores()`` is False; ``deploy_explore = True`` keeps
      the noise) so that they measure the candidate, and the iterate makes no step during
      them (no noise, no critic; with ``deploy_explore`` one step along the block's mean
      gradient at its end). When a block ends, its candidate replaces the deployed theta
      only if its episode costs are lower than the deployed theta's own block with
      confidence ``deploy_confidence`` (0.9): with cycled starts per start (the paired t-test
      of the per-start mean differences), with random starts unpaired, adjusted for how
      costly each episode's start is (``deploy_adjust = "start_cost"``, the default since
      session 13: the analysis of covariance on theta0's cost from the start on the MPC's own
      model, :func:`~mpcmobo.learners.deploy.adjusted_confidence`; ``"none"``: Welch)
      (:func:`~mpcmobo.learners.deploy.paired_confidence`,
      :func:`~mpcmobo.learners.deploy.unpaired_confidence`). The cost is ``deploy_metric``:
      the plain mean stage cost (``"stage_cost"``, the quantity J_eval averages, from the
      learner's own episodes) or f1 (discounted). A promising candidate (confidence at least
      0.5) is run for another block, up to ``deploy_max_runs`` (12) episodes, where that brings
      new starts (random starts, or noisy measurements). A candidate confidently worse than the
      deployed theta (confidence at most ``1 - deploy_confidence``) sends the iterate back to
      the deployed theta, the step rule keeping its state (``deploy_reset``, default True);
    * ``"pooled"`` (the default of sessions 5-11): its best iterate judged by its own episodes
      pooled over nearby iterates (``deploy_bandwidth``, a length in the unit cube) and
      adjusted for their initial states; the deployed theta changes only when another iterate
      is better with probability ``deploy_confidence`` (default 0.99)
      (:class:`~mpcmobo.rl.judge.PooledJudge`);
    * ``"gp"``: the first issue-11 judge, a GP on log f1 of its own episodes over ``(z, c)``
      with ``context = "x0"`` (c the scaled initial state), expected f1 over a fixed sample of
      initial states (:class:`~mpcmobo.learners.deploy.DeployRule`, ``deploy_confidence``
      default 0.9). ``deploy = None`` with ``deploy_confidence`` set means ``"gp"`` (as before);
    * ``"iterate"``: the iterate itself (the behaviour before issue 11).

    Runs checkpointed before the ``deploy`` option existed resume with the rule they were run
    with (the iterate deployed, or ``"gp"`` with ``deploy_confidence``) when ``deploy`` is left
    at its default; runs checkpointed with the pooled judge (sessions 5-11) resume with it.
    """

    name = "mpc-rl"
    # deploy = "verified" (set in _init_judge; see there)
    block_Z_: np.ndarray
    block_id_: np.ndarray
    block_F_: np.ndarray
    block_S_: np.ndarray
    block_C_: np.ndarray
    block_conf_: np.ndarray
    block_G_: np.ndarray

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
        max_step: float | None = 0.1,
        lr_decay: float = 0.0,
        deploy: str | None = None,
        deploy_confidence: float | None = None,
        deploy_bandwidth: float = 0.1,
        deploy_min_runs: int = 6,
        deploy_every: int = 12,
        deploy_max_runs: int | None = None,
        deploy_metric: str = "stage_cost",
        deploy_explore: bool = False,
        deploy_reset: bool = True,
        deploy_adjust: str = "start_cost",
        context: str = "none",
        n_contexts: int = 16,
        incumbent_kappa: float = 0.0,
        contexts: ContextSpec | None = None,
    ) -> None:
        super().__init__(space, theta0, seed)
        check_choice("optimizer", optimizer, STEP_RULES)
        if deploy is not None:
            check_choice("deploy", deploy, DEPLOY_MODES)
        if context not in ("none", "x0"):
            raise ValueError(f"context must be 'none' or 'x0', got {context!r}")
        if context == "x0" and contexts is None:
            raise ValueError("context = 'x0' needs the system's contexts (ContextSpec)")
        self._deploy_option = deploy
        self.lr, self.lr_decay = lr, float(lr_decay)
        self.beta1, self.beta2, self.eps, self.max_step = beta1, beta2, eps, max_step
        self.deploy_confidence, self.deploy_bandwidth = deploy_confidence, deploy_bandwidth
        if int(deploy_min_runs) < 2:
            raise ValueError(f"deploy_min_runs must be at least 2, got {deploy_min_runs}")
        self.deploy_min_runs = int(deploy_min_runs)
        if int(deploy_every) < 0:
            raise ValueError(f"deploy_every must be at least 0, got {deploy_every}")
        self.deploy_every = int(deploy_every)
        cap = 2 * self.deploy_min_runs if deploy_max_runs is None else int(deploy_max_runs)
        if cap < self.deploy_min_runs:
            raise ValueError(
                f"deploy_max_runs must be at least deploy_min_runs ({self.deploy_min_runs}), "
                f"got {deploy_max_runs}"
            )
        self.deploy_max_runs = cap
        self.deploy_metric = check_choice("deploy_metric", deploy_metric, DEPLOY_METRICS)
        self.deploy_explore = bool(deploy_explore)
        self.deploy_reset = bool(deploy_reset)
        self.deploy_adjust = check_choice("deploy_adjust", deploy_adjust, ADJUST_MODES)
        self.context_spec = contexts
        self.contexts = contexts.sample(int(n_contexts)) if context == "x0" else np.zeros((1, 0))  # type: ignore[union-attr]  # checked above
        self.incumbent_kappa = float(incumbent_kappa)
        self._configure(
            optimizer,
            deploy or ("gp" if deploy_confidence is not None else "verified"),
        )
        self.z = space.to_unit(self.theta0)

    def _configure(self, optimizer: str, deploy: str) -> None:
        """Build the step rule and the deployment judge (fresh state)."""
        self.optimizer, self.deploy = optimizer, deploy
        self.rule = self._make_rule(optimizer, self.lr)
        self.deploy_rule = None
        self.pooled = None
        if deploy == "gp":
            conf = 0.9 if self.deploy_confidence is None else float(self.deploy_confidence)
            self.deploy_rule = DeployRule(kappa=self.incumbent_kappa, deploy_confidence=conf)
        elif deploy == "pooled":
            conf = POOLED_CONFIDENCE if self.deploy_confidence is None else self.deploy_confidence
            conf = float(conf)
            self.pooled = PooledJudge(confidence=conf, bandwidth=float(self.deploy_bandwidth))
        elif deploy == "verified":
            conf = VERIFIED_CONFIDENCE if self.deploy_confidence is None else self.deploy_confidence
            self.verified_confidence = check_confidence("deploy_confidence", conf)
        self._init_judge()

    def _make_rule(self, optimizer: str, lr: float) -> StepRule:
        """The step rule ``optimizer`` with this learner's options."""
        kw: dict[str, Any] = {"lr": float(lr)}
        if optimizer == "adam":
            kw.update(beta1=self.beta1, beta2=self.beta2, eps=self.eps, max_step=self.max_step)
        elif optimizer == "sgd":
            kw.update(max_step=self.max_step)
        elif optimizer == "trust":
            kw.update(beta1=self.beta1)
        return STEP_RULES[optimizer](lr_decay=self.lr_decay, **kw)

    # the moments and step count of the rule, under their old names (old checkpoints)
    @property
    def m(self) -> np.ndarray:
        """The step rule's first moment (old name)."""
        return self.rule.m

    @property
    def v(self) -> np.ndarray:
        """The step rule's second moment (old name)."""
        return self.rule.v

    @property
    def t(self) -> int:
        """The step rule's step count (old name)."""
        return self.rule.t

    def _theta(self) -> np.ndarray:
        return self.space.from_unit(self.z, base=self.theta0)

    def _theta_of(self, z: np.ndarray) -> np.ndarray:
        """The theta of the unit-cube point ``z``: exactly theta0 at theta0's own ``z`` (not its
        round trip through z, which J_eval can tell apart on the CSTR)."""
        if np.array_equal(z, self.space.to_unit(self.theta0)):
            return self.theta0.copy()
        return self.space.from_unit(z, base=self.theta0)

    def propose(self) -> np.ndarray:
        """The current theta of the gradient steps; with ``deploy = "verified"`` the candidate
        of the open block (the iterate when the block opened)."""
        if self.deploy == "verified":
            return self._theta_of(self._open_block_z())
        return self._theta()

    def incumbent(self) -> np.ndarray:
        """The deployed theta: the iterate, or with a deployment judge the best verified one."""
        if self.deploy == "iterate":
            return self._theta()
        return self._theta_of(self.deployed_z_)

    def uses_start_cost(self) -> bool:
        """``deploy = "verified"`` with ``deploy_adjust = "start_cost"`` (the default): under
        random starts the blocks' costs are compared adjusted for their starts."""
        return self.deploy == "verified" and self.deploy_adjust == "start_cost"

    def explores(self) -> bool:
        """False for the episodes of a verification block (``deploy = "verified"``, unless
        ``deploy_explore``): they measure the candidate without exploration noise."""
        return not (self.deploy == "verified" and not self.deploy_explore and self._in_block())

    # ------------------------------------------------ verified blocks (deploy = "verified")
    def _block_open(self) -> bool:
        """Whether the last block still needs episodes: fewer than its target,
        ``deploy_min_runs`` or, extended (a promising candidate), a multiple of it."""
        n = len(self.block_Z_)
        if not n:
            return False
        return bool(np.count_nonzero(self.block_id_ == n - 1) < self.block_target_)

    def _in_block(self) -> bool:
        """Whether the next episode belongs to a verification block: the first block (theta0),
        an open one, or a new one after ``deploy_every`` steps."""
        return (
            not len(self.block_Z_) or self._block_open() or self.since_block_ >= self.deploy_every
        )

    def _open_block_z(self) -> np.ndarray:
        """The candidate of the block in progress; the iterate when none is (a new block opens
        at the iterate)."""
        return self.block_Z_[-1] if self._block_open() else self.z.copy()

    def _observe_block(
        self, theta: np.ndarray, result: EpisodeResult, g: np.ndarray | None
    ) -> None:
        """Record the episode in its block (``g``: its gradient, None if invalid). When the
        block is complete, one step along its mean gradient, and its candidate judged against
        the deployed theta (:meth:`_block_confidence`)."""
        z = self.space.to_unit(self.space.clip(theta))
        if not self._block_open():  # a new block
            self.block_Z_ = np.vstack([self.block_Z_, z])
            self.block_G_, self.block_nG_ = np.zeros(self.space.n_theta), 0
            self.block_target_ = self.deploy_min_runs
        n = len(self.block_Z_)
        self.block_id_ = np.append(self.block_id_, n - 1)
        self.block_F_ = np.append(self.block_F_, self._block_cost(result))
        self.block_S_ = np.append(self.block_S_, int(result.start_id))
        self.block_C_ = np.append(self.block_C_, float(result.start_cost))
        if g is not None:
            self.block_G_, self.block_nG_ = self.block_G_ + g, self.block_nG_ + 1
        if self._block_open():
            return
        conf = self._block_confidence(n - 1) if n > 1 else None  # block 0: theta0, the baseline
        cand = self.block_id_ == n - 1
        count = int(np.count_nonzero(cand))
        fresh = self.deploy_explore or bool(np.any(self.block_S_[cand] < 0))
        if conf is not None and 0.5 <= conf < self.verified_confidence and fresh:
            # promising, not yet convincing: run it again from the next starts (up to the cap);
            # not with cycled starts and no noise, where a re-run repeats the same costs
            if count + self.deploy_min_runs <= self.deploy_max_runs:
                self.block_target_ = count + self.deploy_min_runs
                return
        self.since_block_ = 0
        if self.block_nG_:
            self._step(theta, self.block_G_ / self.block_nG_)
        if conf is None:
            return
        self.block_conf_ = np.append(self.block_conf_, conf)
        if conf >= self.verified_confidence:
            self.deployed_block_ = n - 1
            self.deployed_z_ = self.block_Z_[n - 1].copy()
        elif self.deploy_reset and conf <= 1.0 - self.verified_confidence:
            # confidently worse than the deployed theta: the iterate goes back to it (the step
            # rule keeps its state: a fresh Adam's first steps are its largest)
            self.z = self.deployed_z_.copy()

    def _block_cost(self, result: EpisodeResult) -> float:
        """The episode's cost as the blocks compare it (``deploy_metric``): the plain mean stage
        cost (what J_eval averages; f1 where the episode did not report it) or f1 (discounted);
        inf for a failed episode. Not ``result.valid``: a noise-free episode has no critic."""
        f = result.stage_cost if self.deploy_metric == "stage_cost" else result.f1
        if self.deploy_metric == "stage_cost" and np.isnan(f):
            f = result.f1
        return float(f) if np.isfinite(f) else np.inf

    def _block_confidence(self, b: int) -> float:
        """The confidence that block ``b``'s candidate is better than the deployed theta in
        expected episode cost, from the two blocks' own episodes (never J_eval): with cycled
        starts, per start the deployed block's mean cost from it minus the candidate's
        (:func:`~mpcmobo.learners.deploy.paired_confidence` of those differences), with
        random starts the two blocks' costs unpaired
        (:func:`~mpcmobo.learners.deploy.unpaired_confidence`, Welch). A failed episode in the
        candidate's block rules it out."""
        cand = self.block_id_ == b
        dep = self.block_id_ == self.deployed_block_
        if not np.all(np.isfinite(self.block_F_[cand])):
            return 0.0
        S = self.block_S_
        if np.all(S[cand] >= 0) and np.all(S[dep] >= 0):  # cycled starts: like for like
            F = self.block_F_
            d = [  # per start: the two thetas' mean costs from it
                float(np.mean(F[dep & (S == s)])) - float(np.mean(F[cand & (S == s)]))
                for s in np.unique(S[cand])
                if np.any(dep & (S == s))
            ]
            if d:
                return paired_confidence(np.asarray(d))
        if self.deploy_adjust == "start_cost":  # random starts, adjusted for the starts
            C = self.block_C_
            return adjusted_confidence(self.block_F_[dep], self.block_F_[cand], C[dep], C[cand])
        return unpaired_confidence(self.block_F_[dep], self.block_F_[cand])

    # ------------------------------------------------------------ deployment (issue 11)
    def _init_judge(self) -> None:
        from mpcmobo.bo import GPSurrogate

        dc = self.contexts.shape[1]
        self.judge = None if self.deploy_rule is None else GPSurrogate(1, log_outcomes=(True,))
        self.X_ = np.zeros((0, self.space.dim + dc))  # (z, c) of the learner's own episodes
        self.F_ = np.zeros(0)  # their f1
        self.X0_ = np.zeros((0, 0))  # their initial states (the pooled judge)
        self.deployed_z_ = self.space.to_unit(self.theta0)
        # deploy = "verified": the candidate of each block (rows), and per episode its block,
        # cost (inf: failed) and start id; the deployed block (0: theta0's) and each later
        # block's confidence of being better
        self.block_Z_ = np.zeros((0, self.space.dim))
        self.block_id_ = np.zeros(0, dtype=int)
        self.block_F_ = np.zeros(0)
        self.block_S_ = np.zeros(0, dtype=int)
        self.block_C_ = np.zeros(0)  # the start cost of each block episode (deploy_adjust)
        self.block_conf_ = np.zeros(0)
        self.deployed_block_ = 0
        self.block_G_, self.block_nG_ = np.zeros(self.space.n_theta), 0  # the open block's
        self.since_block_ = 0  # steps since the last block ended
        self.block_target_ = self.deploy_min_runs  # the open block's length (extended: more)
        self._judge_pre_fit: dict | None = None
        self._deployed_pre_fit = self.deployed_z_.copy()

    def _observe_deploy(self, theta: np.ndarray, result: EpisodeResult) -> None:
        z = self.space.to_unit(self.space.clip(theta))
        if self.pooled is not None:
            x0 = np.zeros(0) if result.x0 is None else np.asarray(result.x0, float)
            if len(self.F_) == 0:
                self.X0_ = np.zeros((0, len(x0)))
            self.X_ = np.vstack([self.X_, z])
            self.X0_ = np.vstack([self.X0_, x0])
            self.F_ = np.append(self.F_, result.f1)
            self.deployed_z_ = self.pooled.choose(self.X_, self.X0_, self.F_, self.deployed_z_)
            return
        dc = self.contexts.shape[1]
        c = np.zeros(0) if dc == 0 else self.context_spec.unit(result.x0)  # type: ignore[union-attr,arg-type]  # dc > 0: context x0
        self.X_ = np.vstack([self.X_, np.concatenate([z, c])])
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
        skipped. With ``deploy = "verified"``, an episode of a verification block adds its
        gradient to the block's and the block's mean gradient makes one step when it ends."""
        self.n_observed += 1
        g = np.asarray(result.grad, dtype=float)
        ok = result.critic_ok and bool(np.all(np.isfinite(g))) and result.valid
        if self.deploy == "verified" and self._in_block():
            self._observe_block(theta, result, g if ok else None)
            return
        if self.deploy == "verified":
            self.since_block_ += 1
        elif self.deploy != "iterate":
            self._observe_deploy(theta, result)
        if ok:
            self._step(theta, g)

    def _step(self, theta: np.ndarray, g: np.ndarray) -> None:
        """One step of the rule from the iterate along the gradient ``g`` taken at ``theta``."""
        theta = self.space.clip(theta)
        free = self.space.free
        if self.rule.coordinates == "unit":
            gz = g[free] * self.space.dtheta_dz(theta)
            self.z = np.clip(self.z - self.rule.step(gz), 0.0, 1.0)  # projection onto the bounds
        else:  # a step in theta itself, projected onto the bounds
            new = theta.copy()
            new[free] = new[free] - self.rule.step(g[free])
            self.z = self.space.to_unit(self.space.clip(new))

    def state_dict(self) -> dict:
        """The base state plus the Adam state (z, m, v, t) and the deploy rule's state."""
        d = super().state_dict()
        d["z"] = self.z.copy()
        d["optimizer"], d["deploy"] = self.optimizer, self.deploy
        d.update(self.rule.state_dict())  # m, v, t
        if self.pooled is not None:
            d.update(
                {
                    "judge_X": self.X_.copy(),
                    "judge_F": self.F_.copy(),
                    "judge_X0": self.X0_.copy(),
                    "deployed_z": self.deployed_z_.copy(),
                }
            )
        elif self.deploy == "verified":
            d.update(
                {
                    "block_Z": self.block_Z_.copy(),
                    "block_id": self.block_id_.copy(),
                    "block_F": self.block_F_.copy(),
                    "block_S": self.block_S_.copy(),
                    "block_C": self.block_C_.copy(),
                    "deploy_adjust": self.deploy_adjust,
                    "block_conf": self.block_conf_.copy(),
                    "deployed_block": self.deployed_block_,
                    "deployed_z": self.deployed_z_.copy(),
                    "block_G": self.block_G_.copy(),
                    "block_nG": self.block_nG_,
                    "since_block": self.since_block_,
                    "block_target": self.block_target_,
                }
            )
        elif self.deploy_rule is not None:
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
        # a checkpoint from before the step-rule and deploy options: the rules it ran with
        optimizer = state.get("optimizer", self.optimizer)
        legacy_deploy = "gp" if self.deploy_confidence is not None else "iterate"
        deploy = state.get("deploy", self._deploy_option or legacy_deploy)
        if (optimizer, deploy) != (self.optimizer, self.deploy):
            self._configure(optimizer, deploy)
        self.z = np.array(state["z"], dtype=float)
        self.rule.load_state_dict(state)
        self._init_judge()
        if self.pooled is not None:
            if "judge_X" in state:
                self.X_ = np.array(state["judge_X"], float)
                self.F_ = np.array(state["judge_F"], float)
                self.X0_ = np.array(state["judge_X0"], float)
                self.deployed_z_ = np.array(state["deployed_z"], float)
        elif self.deploy == "verified" and "block_Z" in state:
            self.block_Z_ = np.array(state["block_Z"], float).reshape(-1, self.space.dim)
            self.block_id_ = np.array(state["block_id"], int)
            self.block_F_ = np.array(state["block_F"], float)
            self.block_S_ = np.array(state["block_S"], int)
            # a checkpoint from before session 13 has no start costs: it resumes unadjusted
            self.block_C_ = np.array(state.get("block_C", np.full(len(self.block_S_), np.nan)))
            self.deploy_adjust = state.get("deploy_adjust", "none")
            self.block_conf_ = np.array(state["block_conf"], float)
            self.deployed_block_ = int(state["deployed_block"])
            self.deployed_z_ = np.array(state["deployed_z"], float)
            self.block_G_ = np.array(state["block_G"], float)
            self.block_nG_ = int(state["block_nG"])
            self.since_block_ = int(state["since_block"])
            self.block_target_ = int(state["block_target"])
        elif self.deploy_rule is not None and "judge_X" in state:
            # else a checkpoint without deployment: start afresh
            self.X_ = np.array(state["judge_X"], float)
            self.F_ = np.array(state["judge_F"], float)
            self.deployed_z_ = np.array(state["deployed_pre_fit"], float)
            if state["judge_pre_fit"] is not None:
                self.judge.load_state_dict(state["judge_pre_fit"])  # type: ignore[union-attr]
                self._judge_fit()
