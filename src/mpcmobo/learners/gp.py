"""The GP learners' loop: propose a theta, observe its episode, refit, let the policy deploy.

``propose``: the initial design (theta0, then Sobol points in the first trust region), then
the deployment policy's check if it wants one (a candidate run again, or the deployed theta
run as a baseline), else the acquisition's best point in the trust region around the deployed
theta. ``observe``: append the episode to the evidence (``observe_simulated``: a refused
candidate's episode on the identified model, for the GP alone), refit the GP (start effects
under cycled starts; f1 relative to the start cost under the random-start policy), let the policy
decide what is deployed, and move the trust region (a proposal that becomes the deployed
theta is a success; a verification is neither). :class:`BOLearner` models f1 with expected
improvement (eq. EI); :mod:`mpcmobo.learners.mobo` adds the multi-objective learners.

Resume is exact and immediate: the state holds the evidence, the GP's state after the last fit
and that fit's decision, and loading it rebuilds the fitted GP without fitting
(:meth:`~mpcmobo.bo.GPSurrogate.restore`).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from scipy.stats import qmc

from mpcmobo.bo import AcqfSearch, GPSurrogate, propose_ei
from mpcmobo.bo.acquisition import Box
from mpcmobo.bo.trust import TrustRegion, TrustState
from mpcmobo.learners.base import EpisodeResult, Learner, Starts
from mpcmobo.learners.deploy import DeployPolicy, EvidencePolicy, make_policy
from mpcmobo.learners.evidence import SIMULATED, Evidence, theta_key
from mpcmobo.learners.options import BOOptions
from mpcmobo.learners.prediction import Twin
from mpcmobo.systems.space import SearchSpace

__all__ = ["BOLearner", "GPLearner"]

REFIT_FRACTION = 0.1  # above 100 episodes, a full GP fit after every 10% growth of the data


class GPLearner(Learner):
    """The loop shared by the GP learners (module docstring); subclasses set the modelled
    ``outputs``, which of them are modelled in log, and :meth:`_acquire`."""

    outputs: ClassVar[tuple[int, ...]] = (0,)
    log_outputs: ClassVar[tuple[bool, ...]] = (True,)
    options_class: ClassVar[type[BOOptions]] = BOOptions

    def __init__(
        self,
        space: SearchSpace,
        theta0: np.ndarray,
        seed: int = 0,
        options: BOOptions | None = None,
        *,
        starts: Starts | None = None,
    ) -> None:
        super().__init__(space, theta0, seed, starts=starts)
        self.options = self.options_class() if options is None else options
        if not isinstance(self.options, self.options_class):
            raise TypeError(f"{self.name} takes {self.options_class.__name__}")
        o = self.options
        self.policy: DeployPolicy = make_policy(o.deploy, self.starts, o.incumbent_kappa)
        tr = o.trust_region
        self.trust_region = None if tr is False else TrustRegion(**tr.model_dump())
        self.search = AcqfSearch(o.search.num_restarts, o.search.raw_samples, o.search.maxiter)
        self.surrogate = GPSurrogate(
            len(self.outputs),
            refit_every=o.refit_every,
            refit_fraction=REFIT_FRACTION,
            log_outcomes=self.log_outputs,
            group_outputs=self.log_outputs,  # start offsets on the log-modelled costs
        )
        self.design = self._initial_design()
        self.evidence_ = Evidence(space.dim, space.n_theta, len(self.outputs))
        self.deployed_z_ = space.to_unit(self.theta0)
        self.verify_z_: np.ndarray | None = None  # a candidate the policy wants run again
        self.trust_: TrustState | None = (
            None if self.trust_region is None else self.trust_region.start()
        )
        self.fitted_ = False
        self.pending_: tuple[str, bytes] | None = None  # the last proposal's kind and theta
        self.n_seeded_ = 0  # episodes given before the design (:meth:`seed_with`)

    # ------------------------------------------------------------------ the design
    def _initial_design(self) -> np.ndarray:
        """theta0, then scrambled Sobol points (seeded) in the first trust region (or the
        whole cube): ``n_init`` rows in unit coordinates."""
        n_init = self.options.n_init
        z0 = self.space.to_unit(self.theta0)
        sob = qmc.Sobol(d=self.space.dim, scramble=True, seed=self.seed).random(
            max(1, 2 ** int(np.ceil(np.log2(max(1, n_init)))))
        )
        if self.trust_region is not None:
            lo, hi = self.trust_region.box(z0, self.trust_region.length_init)
            sob = lo + (hi - lo) * sob
        return np.vstack([z0, sob])[:n_init]

    # ------------------------------------------------------------------ the loop
    def incumbent(self) -> np.ndarray:
        """The deployed theta."""
        return self.theta_of(self.deployed_z_)

    def verifying(self) -> np.ndarray | None:
        """The candidate the deployment policy wants run again (None: none)."""
        return None if self.verify_z_ is None else self.theta_of(self.verify_z_)

    def uses_start_cost(self) -> bool:
        """Whether the policy reads the episodes' start costs (the evidence policies)."""
        return self.policy.uses_start_cost

    def seed_with(self, episodes: list[tuple[np.ndarray, EpisodeResult]]) -> None:
        """Start from episodes of theta0 run before the learner (the identification's): they
        are evidence, and the initial design goes on from its second point."""
        if len(self.evidence_):
            raise ValueError("seed_with needs a learner that has observed nothing yet")
        for theta, result in episodes:
            self._append(theta, result, "seed")
        self.n_seeded_ = len(episodes) - 1 if episodes else 0  # theta0 is the design's first
        self._fit()

    def use_twin(self, twin: Twin) -> None:
        """Let ``twin`` judge the deployments (an evidence policy; the incumbent rule has no
        tests): :meth:`~mpcmobo.learners.deploy.DeployPolicy.decide` then deploys on the
        prediction-powered test."""
        if isinstance(self.policy, EvidencePolicy):
            self.policy.twin = twin.on(self.theta_of)

    def propose(self) -> np.ndarray:
        """The design's next point, the policy's check, or the acquisition's point."""
        n = len(self.evidence_) - self.n_seeded_
        if n < self.options.n_init:
            return self._proposed("design", self.design[n])
        if not self.fitted_:  # every observation so far failed: keep exploring
            u = self.rng.uniform(size=self.space.dim)
            box = self._trust_box()
            return self._proposed("design", u if box is None else box[0] + (box[1] - box[0]) * u)
        check = self.policy.next_check(self.evidence_, self.deployed_z_, self.verify_z_)
        if check is not None:
            return self._proposed(*check)
        return self._proposed("search", self._acquire(int(self.rng.integers(2**31 - 1))))

    def _proposed(self, kind: str, z: np.ndarray) -> np.ndarray:
        """Remember what the proposal is and return its theta."""
        self.pending_ = (kind, theta_key(z))
        return self.theta_of(z)

    def observe(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """Append the episode, refit, decide, move the trust region."""
        z = self.space.to_unit(self.space.clip(theta))
        kind = "other"  # not the last proposal (a failed proposal, or a theta given by hand)
        if self.pending_ is not None and self.pending_[1] == theta_key(z):
            kind = self.pending_[0]
        self.pending_ = None
        self._append(theta, result, kind)
        self._fit()

    def learns_in_simulation(self) -> bool:
        """The GP learns from a refused candidate's simulated episode."""
        return True

    def observe_simulated(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """Append the simulated episode as a ``"simulated"`` row (the GP's, never a
        deployment's evidence), refit, decide, move the trust region as for a plant episode of
        the candidate."""
        self.pending_ = None
        self._append(theta, result, SIMULATED)
        self._fit()

    def _append(self, theta: np.ndarray, result: EpisodeResult, kind: str) -> None:
        z = self.space.to_unit(self.space.clip(theta))
        y = np.asarray(result.objectives, dtype=float)[list(self.outputs)]
        self.evidence_.append(
            z,
            y,
            result.grad,
            result.start_id,
            result.start_cost,
            kind,
            cost=result.stage_cost,
            replay=result.replay,
        )
        self.n_observed += 1

    def _model_Y(self) -> np.ndarray:
        """The objectives as the GP sees them: under the random-start evidence policy f1
        divided by the episode's start cost (so that the GP does not read the luck of the
        start as an effect of theta; rows without a usable start cost take the median of the
        others), else as observed."""
        ev = self.evidence_
        if not self.policy.relative or not len(ev):
            return ev.Y
        s = ev.start_costs
        ok = np.isfinite(s) & (s > 0)
        if not np.any(ok):
            return ev.Y
        Y = ev.Y.copy()
        Y[:, 0] = Y[:, 0] / np.where(ok, s, np.median(s[ok]))
        return Y

    def _fit(self) -> None:
        """Fit the GP on the finite episodes, let the policy decide, move the trust region."""
        previous = self.deployed_z_.copy()
        self._before_fit()
        ev = self.evidence_
        if np.count_nonzero(ev.finite()) < 2:
            self.fitted_ = False
        else:
            self.surrogate.fit(ev.Z, self._model_Y(), groups=ev.starts)
            self.fitted_ = True
            seed = 1234 + len(ev)
            decision = self.policy.decide(ev, self.surrogate, self.deployed_z_, seed)
            self.deployed_z_, self.verify_z_ = decision.deployed, decision.verify
        self._update_trust(previous)

    def _before_fit(self) -> None:
        """A hook of the subclasses, run before every fit."""

    # ------------------------------------------------------------------ the trust region
    def _update_trust(self, previous: np.ndarray) -> None:
        """One step of the trust region per episode after the design: a success when the
        theta just run became the deployed theta, a failure otherwise; under an evidence
        policy a verification episode (a theta run before) or a search point that earned one
        is neither."""
        ev = self.evidence_
        if self.trust_region is None or self.trust_ is None:
            return
        if len(ev) - self.n_seeded_ <= self.options.n_init:
            return
        last = theta_key(ev.Z[-1])
        success = theta_key(self.deployed_z_) == last and theta_key(previous) != last
        if self.policy.gathers_evidence and not success:
            earned = self.verify_z_ is not None and theta_key(self.verify_z_) == last
            if earned or ev.ran(ev.Z[-1]):
                return
        self.trust_ = self.trust_region.update(self.trust_, success, self.space.dim)

    def _trust_box(self) -> Box | None:
        """The trust region (lower, upper) around the deployed theta, or None."""
        if self.trust_region is None or self.trust_ is None:
            return None
        return self.trust_region.box(self.deployed_z_, self.trust_.length)

    def _acquire(self, seed: int) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """The base state, the evidence, the GP's state after the last fit and its decision."""
        d = super().state_dict()
        d["evidence"] = self.evidence_.state_dict()
        d["surrogate"] = self.surrogate.state_dict()
        d["fitted"] = self.fitted_
        d["deployed"] = self.deployed_z_.copy()
        d["verify"] = None if self.verify_z_ is None else self.verify_z_.copy()
        d["trust"] = None if self.trust_ is None else self.trust_.to_dict()
        d["n_seeded"] = self.n_seeded_
        d["pending"] = self.pending_  # a proposal not yet observed (ask and tell)
        return d

    def load_state_dict(self, state: dict) -> None:
        """Continue from a :meth:`state_dict`: the fitted GP is rebuilt as it was, without
        fitting."""
        super().load_state_dict(state)
        self.evidence_.load_state_dict(state["evidence"])
        self.n_seeded_ = int(state["n_seeded"])
        self.pending_ = state["pending"]
        self.deployed_z_ = np.array(state["deployed"], float)
        verify = state["verify"]
        self.verify_z_ = None if verify is None else np.array(verify, float)
        self.trust_ = None if state["trust"] is None else TrustState.from_dict(state["trust"])
        self.fitted_ = bool(state["fitted"])
        ev = self.evidence_
        if self.fitted_:
            self.surrogate.restore(ev.Z, self._model_Y(), ev.starts, state["surrogate"])
        else:
            self.surrogate.load_state_dict(state["surrogate"])


class BOLearner(GPLearner):
    """Single-objective BO: a GP on f1 (eq. GP, mean_var) and log expected improvement (eq. EI)."""

    name = "bo"

    def _acquire(self, seed: int) -> np.ndarray:
        return propose_ei(
            self.surrogate,
            self.evidence_.Z,
            self._model_Y(),
            seed=seed,
            search=self.search,
            box=self._trust_box(),
        )
