"""MPC-RL: compatible deterministic policy gradient steps on theta (eq. theta).

The learner steps its iterate along each episode's CDPG gradient (eq. DPG) with its step rule
(:mod:`mpcmobo.rl.steps`: Adam in the unit cube of the search space, or the paper's plain step
in theta), projected onto the search bounds; an episode without a valid gradient makes no step.
What it deploys is a policy of its own:

* ``"verified"`` (:class:`VerifiedBlocks`): every ``every`` steps the iterate is frozen for a
  block of ``runs`` episodes without exploration noise, and replaces the deployed theta only
  when the block's episode costs (the plain mean stage cost, what J_eval averages) are
  cheaper than the deployed theta's own block with ``confidence``: per start under cycled
  starts (:func:`~mpcmobo.learners.confidence.paired_confidence`), adjusted for the starts'
  cost under random starts (:func:`~mpcmobo.learners.confidence.adjusted_confidence`); once a
  twin judges (identify-first), the prediction-powered test of the same episodes
  (:func:`~mpcmobo.learners.confidence.twin_confidence`). The first block measures theta0;
* ``"iterate"`` (the paper's rule): the iterate itself.
"""

from __future__ import annotations

import numpy as np

from mpcmobo.learners.base import EpisodeResult, Learner, Starts
from mpcmobo.learners.confidence import adjusted_confidence, paired_confidence
from mpcmobo.learners.evidence import Evidence
from mpcmobo.learners.judge import paired_differences, twin_verdict
from mpcmobo.learners.options import AdamStep, MPCRLOptions, VerifiedDeploy
from mpcmobo.learners.prediction import Twin
from mpcmobo.rl.steps import Adam, PlainGradient, StepRule
from mpcmobo.systems.space import SearchSpace

__all__ = ["MPCRL", "VerifiedBlocks"]


def make_step_rule(options: MPCRLOptions) -> StepRule:
    """The step rule of the learner's ``optimizer`` option."""
    o = options.optimizer
    if isinstance(o, AdamStep):
        return Adam(lr=o.lr, max_step=o.max_step)
    return PlainGradient(lr=o.lr)


class VerifiedBlocks:
    """The verification blocks of ``deploy = "verified"`` (module docstring): the block
    episodes in an :class:`~mpcmobo.learners.evidence.Evidence` (one group per block; the
    cost judged is the plain mean stage cost, f1 where it is unknown, inf for a failed
    episode), per block its candidate, and the deployed block (0: theta0's)."""

    def __init__(self, options: VerifiedDeploy, starts: Starts, dim: int, n_theta: int) -> None:
        self.options = options
        self.random = starts.mode == "random"  # a re-run from new starts brings new evidence
        self.n_theta = n_theta
        self.evidence_ = Evidence(dim, n_theta, 1)
        self.candidates_ = np.zeros((0, dim))  # the candidate of each block
        self.twin: Twin | None = None  # the twin that judges, if any (module docstring)
        self.conf_ = np.zeros(0)  # each later block's confidence of being cheaper
        self.deployed_ = 0
        self.G_, self.nG_ = np.zeros(n_theta), 0  # the open block's summed gradient
        self.since_ = 0  # gradient steps since the last block ended
        self.target_ = options.runs  # the open block's length (a promising one: more)

    def is_open(self) -> bool:
        """Whether the last block still needs episodes."""
        n = len(self.candidates_)
        return bool(n) and len(self.evidence_.group(n - 1)) < self.target_

    def in_block(self) -> bool:
        """Whether the next episode belongs to a block: the first, an open one, or a new one
        after ``every`` steps."""
        return not len(self.candidates_) or self.is_open() or self.since_ >= self.options.every

    def candidate(self, iterate: np.ndarray) -> np.ndarray:
        """The open block's candidate; the iterate when none is open (a new block opens
        there)."""
        return self.candidates_[-1] if self.is_open() else iterate.copy()

    def deployed_point(self) -> np.ndarray:
        """The deployed block's candidate (unit cube)."""
        return self.candidates_[self.deployed_]

    def stepped(self) -> None:
        """A gradient step outside the blocks (a new block opens after ``every``)."""
        self.since_ += 1

    def observe(
        self, z: np.ndarray, result: EpisodeResult, g: np.ndarray | None
    ) -> tuple[np.ndarray | None, float | None]:
        """Record a block episode (``g``: its gradient, None if invalid). When the block ends:
        the block's mean gradient (None without one) and its confidence (None for theta0's)."""
        if not self.is_open():
            self.candidates_ = np.vstack([self.candidates_, z])
            self.G_, self.nG_ = np.zeros(self.n_theta), 0
            self.target_ = self.options.runs
        n = len(self.candidates_)
        f = result.f1 if np.isnan(result.stage_cost) else result.stage_cost
        f = float(f) if np.isfinite(f) else np.inf
        self.evidence_.append(
            z,
            np.array([f]),
            np.zeros(self.n_theta),
            result.start_id,
            result.start_cost,
            "verify",
            cost=f,
            replay=result.replay,
            group=n - 1,
        )
        if g is not None:
            self.G_, self.nG_ = self.G_ + g, self.nG_ + 1
        if self.is_open():
            return None, None
        conf = self.confidence(n - 1) if n > 1 else None
        count = len(self.evidence_.group(n - 1))
        promising = conf is not None and 0.5 <= conf < self.options.confidence
        if promising and self.random and count + self.options.runs <= self.options.max_runs:
            self.target_ = count + self.options.runs  # run it again from new starts
            return None, None
        self.since_ = 0
        step = self.G_ / self.nG_ if self.nG_ else None
        if conf is not None:
            self.conf_ = np.append(self.conf_, conf)
            if conf >= self.options.confidence:
                self.deployed_ = n - 1
        return step, conf

    def confidence(self, b: int) -> float:
        """The confidence that block ``b``'s candidate is cheaper than the deployed theta, from
        the two blocks' own episodes (:mod:`mpcmobo.learners.judge`): per start the deployed
        block's mean cost minus the candidate's (paired), else adjusted for the starts' costs;
        once a twin judges, its test; a failed episode in the candidate's block rules it out."""
        ev = self.evidence_
        cand, dep = ev.group(b), ev.group(self.deployed_)
        F, S = ev.Y[:, 0], ev.starts
        if not np.all(np.isfinite(F[cand])):
            return 0.0
        paired = bool(np.all(S[cand] >= 0) and np.all(S[dep] >= 0))  # cycled: like for like
        if self.twin is not None:
            points = (self.candidates_[self.deployed_], self.candidates_[b])
            return twin_verdict(ev, self.twin, (dep, cand), points, paired)
        if paired:
            d = paired_differences(F, S, cand, dep, per="start")
            if len(d):
                return paired_confidence(d)
        return adjusted_confidence(F[dep], F[cand], ev.start_costs[dep], ev.start_costs[cand])

    def state_dict(self) -> dict:
        """The blocks' evidence and candidates, and the open block's progress."""
        return {
            "evidence": self.evidence_.state_dict(),
            "candidates": self.candidates_.copy(),
            "conf": self.conf_.copy(),
            "deployed": self.deployed_,
            "G": self.G_.copy(),
            "nG": self.nG_,
            "since": self.since_,
            "target": self.target_,
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`."""
        self.evidence_.load_state_dict(state["evidence"])
        self.candidates_ = np.array(state["candidates"], float).reshape(
            -1, self.candidates_.shape[1]
        )
        self.conf_ = np.array(state["conf"], float)
        self.deployed_ = int(state["deployed"])
        self.G_ = np.array(state["G"], float)
        self.nG_ = int(state["nG"])
        self.since_ = int(state["since"])
        self.target_ = int(state["target"])


def _gradient(result: EpisodeResult) -> np.ndarray | None:
    """The episode's CDPG gradient where it is valid (a critic, finite), else None."""
    g = np.asarray(result.grad, dtype=float)
    ok = result.critic_ok and bool(np.all(np.isfinite(g))) and result.valid
    return g if ok else None


class MPCRL(Learner):
    """``theta <- theta - alpha grad_theta J`` (eq. theta) with a deployment policy (module
    docstring)."""

    name = "mpc-rl"
    options_class = MPCRLOptions

    def __init__(
        self,
        space: SearchSpace,
        theta0: np.ndarray,
        seed: int = 0,
        options: MPCRLOptions | None = None,
        *,
        starts: Starts | None = None,
    ) -> None:
        super().__init__(space, theta0, seed, starts=starts)
        self.options = MPCRLOptions() if options is None else options
        if not isinstance(self.options, MPCRLOptions):
            raise TypeError("mpc-rl takes MPCRLOptions")
        self.rule = make_step_rule(self.options)
        d = self.options.deploy
        self.blocks_ = (
            VerifiedBlocks(d, self.starts, space.dim, space.n_theta)
            if isinstance(d, VerifiedDeploy)
            else None
        )
        self.z_ = space.to_unit(self.theta0)  # the iterate

    def propose(self) -> np.ndarray:
        """The iterate; under verification the candidate of the open block."""
        if self.blocks_ is not None:
            return self.theta_of(self.blocks_.candidate(self.z_))
        return self.space.from_unit(self.z_, base=self.theta0)

    def incumbent(self) -> np.ndarray:
        """The deployed theta: the iterate, or the last verified candidate."""
        if self.blocks_ is None:
            return self.space.from_unit(self.z_, base=self.theta0)
        b = self.blocks_
        if not len(b.candidates_):
            return self.theta_of(self.space.to_unit(self.theta0))
        return self.theta_of(b.deployed_point())

    def verifying(self) -> np.ndarray | None:
        """The candidate of the open verification block (None: none is open)."""
        if self.blocks_ is None or not self.blocks_.is_open():
            return None
        return self.theta_of(self.blocks_.candidates_[-1])

    def use_twin(self, twin: Twin) -> None:
        """Let ``twin`` judge the verification blocks (``deploy = "verified"``)."""
        if self.blocks_ is not None:
            self.blocks_.twin = twin.on(self.theta_of)

    def uses_start_cost(self) -> bool:
        """Verification reads the episodes' start costs (random starts' covariate)."""
        return self.blocks_ is not None

    def explores(self) -> bool:
        """False for the episodes of a verification block: they measure the candidate."""
        return not (self.blocks_ is not None and self.blocks_.in_block())

    def observe(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """One step along the episode's CDPG gradient; a block episode adds its gradient to
        the block's, whose mean makes one step when the block ends. An episode of another
        theta than the block's candidate (the exploration budget kept the candidate off the
        plant and the deployed theta ran instead) is no evidence of the candidate: the block
        waits for the candidate's own episodes."""
        self.n_observed += 1
        g = _gradient(result)
        b = self.blocks_
        if b is not None and b.in_block():
            if not np.array_equal(np.asarray(theta, float), self.theta_of(b.candidate(self.z_))):
                return
            z = self.space.to_unit(self.space.clip(theta))
            step, conf = b.observe(z, result, g)
            if step is not None:
                self._step(theta, step)
            c = b.options.confidence
            if conf is not None and conf < c and conf <= 1.0 - c:
                # confidently worse than the deployed theta: the iterate goes back to it (the
                # step rule keeps its state: a fresh Adam's first steps are its largest)
                self.z_ = b.deployed_point().copy()
            return
        if b is not None:
            b.stepped()
        if g is not None:
            self._step(theta, g)

    def learns_in_simulation(self) -> bool:
        """MPC-RL steps along a refused exploring episode's simulated gradient; a
        verification block's episodes (:meth:`explores` False) are the plant's."""
        return self.explores()

    def observe_simulated(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """One step along the CDPG gradient of the refused candidate's episode simulated on
        the identified model; nothing inside a verification block (its evidence is the
        plant's). The step counts nothing towards the next block: the plant's episode does."""
        g = _gradient(result)
        if self.explores() and g is not None:
            self._step(theta, g)

    def _step(self, theta: np.ndarray, g: np.ndarray) -> None:
        """One step of the rule from the iterate along the gradient ``g`` taken at ``theta``."""
        theta = self.space.clip(theta)
        free = self.space.free
        if self.rule.coordinates == "unit":
            gz = g[free] * self.space.dtheta_dz(theta)
            self.z_ = np.clip(self.z_ - self.rule.step(gz), 0.0, 1.0)  # projected on the bounds
        else:  # a step in theta itself, projected onto the bounds
            new = theta.copy()
            new[free] = new[free] - self.rule.step(g[free])
            self.z_ = self.space.to_unit(self.space.clip(new))

    def state_dict(self) -> dict:
        """The base state, the iterate, the step rule's state and the blocks."""
        d = super().state_dict()
        d["z"] = self.z_.copy()
        d["rule"] = self.rule.state_dict()
        d["blocks"] = None if self.blocks_ is None else self.blocks_.state_dict()
        return d

    def load_state_dict(self, state: dict) -> None:
        """Continue from a :meth:`state_dict`."""
        super().load_state_dict(state)
        self.z_ = np.array(state["z"], dtype=float)
        self.rule.load_state_dict(state["rule"])
        if self.blocks_ is not None:
            self.blocks_.load_state_dict(state["blocks"])
