"""Identify first, then tune: the MPC's model fitted from the plant's transitions.

:class:`ModelSwitch` decides between the deployed theta and the candidate that puts the model
identified from every plant transition so far into it (:class:`~mpcmobo.identify.ModelFit`,
refitted once the transitions have grown by ``REFIT_GROWTH``: after every episode for the
first ten, then ever more rarely). A candidate is made once the fit predicts held-out
transitions better than the nominal model, and until its first episode it follows the fit. It
is deployed only on the evidence of its own episodes against the deployed theta's (the GP
learners' rule, :func:`~mpcmobo.learners.deploy.evidence_policy`); one the evidence does not
support, or with a failed episode, is dropped (one left unsure lends its episodes to the next:
``ModelSwitch._judged``). A new candidate comes whenever the fit moves away from the deployed
model by ``MOVED`` standard deviations and by ``RESOLUTION`` of a value (noise-free data give
standard deviations near zero), and from a dropped one by ``MOVED``.

* :class:`IdentifyLearner` (``identify``): the switch alone, the certainty-equivalent
  baseline that a control engineer tries first.
* :class:`IdentifyFirst`: the switch until it has settled, then any other learner built with
  the deployed theta as its theta0. The switch has settled once a deployed model has not been
  left behind by the fit; after a dropped candidate, once no new one has come for a
  verification's worth of episodes (``min_runs``; cycled starts: a cycle); or, once an
  identified model is deployed, after ``MAX_DECISIONS`` decisions (under structural mismatch
  the fit moves as data come in: the learners tune from the model ``identify`` converges to,
  not from the first; drops alone would leave them tuning the nominal model). Settled on an
  identified model, theta is tuned on the twin, the closed loop on that model
  (:mod:`mpcmobo.learners.twin`), and the twin's theta, if cheaper there, is the switch's last
  candidate, judged by that model's twin (:class:`~mpcmobo.learners.twin.Twin`), as the
  tuning learner's candidates are: both thetas' MPC then runs the twin's model.

Under random starts a fitted candidate's tests adjust each episode's cost by the identified
model's prediction of it (the candidate's closed loop on that model from the episode's start)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, replace
from typing import Any

import numpy as np

from mpcmobo.identify import Identification, ModelFit, Transitions
from mpcmobo.learners.base import EpisodeResult, Learner, Starts, replays_from_state
from mpcmobo.learners.deploy import RandomEvidence, evidence_policy
from mpcmobo.learners.evidence import Evidence, theta_key
from mpcmobo.learners.options import EvidenceDeploy, IdentifyOptions
from mpcmobo.learners.twin import TWIN_STARTS, StartCosts, Twin, TwinResult, tune_on_twin
from mpcmobo.systems.space import SearchSpace

__all__ = ["IdentifyFirst", "IdentifyLearner", "ModelSwitch"]

MOVED = 2.0  # a new candidate once the fit moves this many standard deviations
RESOLUTION = 1e-3  # ... and by more than this fraction of a value (noise-free data: std ~ 0)
REFIT_GROWTH = 0.1  # a refit once the transitions have grown by 10% since the last fit
MAX_DECISIONS = 2  # identify-first tuning starts after this many decisions (a model deployed)


class ModelSwitch:
    """The deployed theta, the identified candidate and the evidence between them (module
    docstring). Thetas are kept as they are (the evidence's points are full thetas)."""

    def __init__(
        self,
        fit: ModelFit,
        theta0: np.ndarray,
        starts: Starts,
        deploy: EvidenceDeploy,
        seed: int = 0,
    ) -> None:
        self.fit = fit
        self.seed = int(seed)  # the twin's simulated starts
        self.policy = evidence_policy(deploy, starts, kappa=0.0)
        n = len(theta0)
        self.transitions_ = Transitions.empty(fit.system.nx, fit.system.nu)
        self.identification_: Identification | None = None
        self.evidence_ = Evidence(n, n, 1)
        self.deployed_ = np.array(theta0, float)
        self.candidate_: np.ndarray | None = None
        self.tried_: np.ndarray | None = None  # the estimate of the last candidate
        self.follows_fit_ = True  # the candidate is the fit's (not one offered: :meth:`offer`)
        self.decisions_ = 0  # candidates deployed or dropped
        self.waiting_ = 0  # episodes since the last decision without a new candidate
        # fitted candidates the test left unsure since the last deployment (their episodes
        # count as the candidate's: :meth:`_judged`)
        self.pool_: list[np.ndarray] = []
        # the start covariate's controller and model (None: theta0 on the nominal model)
        self.twin_: tuple[np.ndarray, np.ndarray] | None = None
        self.deployed_params_: np.ndarray | None = None  # the deployed theta's identified model
        self.start_costs: StartCosts | None = None  # the loop's closed loops (use_start_costs)

    # ------------------------------------------------------------------ episodes
    def observe(self, theta: np.ndarray, result: EpisodeResult, kind: str) -> None:
        """The episode's transitions (a refit) and, if it ran the deployed theta or the
        candidate, its cost as evidence; then the decision on the candidate."""
        if result.states is not None and result.inputs is not None:
            self.transitions_.add_episode(result.states, result.inputs)
        if theta_key(theta) in {theta_key(self.deployed_), self._candidate_key()}:
            y = np.array([result.f1])
            self.evidence_.append(theta, y, np.zeros(len(theta)), result.start_id,
                                  result.start_cost, kind, cost=result.stage_cost,
                                  replay=result.replay)  # fmt: skip
        self.refit()
        self.decide()

    def _candidate_key(self) -> bytes | None:
        return None if self.candidate_ is None else theta_key(self.candidate_)

    def refit(self) -> None:
        """Fit the model on every transition so far (warm-started from the last fit), once
        they have grown by ``REFIT_GROWTH`` since the last fit."""
        n, last = len(self.transitions_), self.identification_
        if n == 0 or (last is not None and n < (1 + REFIT_GROWTH) * last.n):
            return
        fit = self.fit.fit(self.transitions_, start=None if last is None else last.estimate)
        if fit.success:
            self.identification_ = fit

    def decide(self) -> None:
        """Deploy or drop the candidate on its evidence; else make one from the fit."""
        if self.candidate_ is None:
            self._propose_candidate()
            if self.candidate_ is None and self.decisions_:
                self.waiting_ += 1
            return
        ev, p, c, d = self.evidence_, self.policy, self.candidate_, self.deployed_
        if theta_key(c) in ev.failed():  # an episode of the candidate diverged
            self._decided()
            return
        if self.follows_fit_ and ev.runs(c) == 0:  # not run yet (a failed run is ruled out above)
            self._propose_candidate(refresh=True)
            return
        runs, own = p.runs(ev, c, d), p.runs(ev, d, d)
        if runs < p.min_runs or own < p.min_runs:
            return
        conf = p.verdict(self._judged(), None, c, d)
        if conf >= p.confidence:
            self.deployed_ = c
            self.deployed_params_ = None if self.twin_ is None else self.twin_[1].copy()
            self.pool_ = []
            self._decided()
            self._propose_candidate()  # has the fit moved on while the candidate ran?
        elif conf < 0.5:
            self.pool_ = []
            self._decided()
        elif runs >= p.max_runs:
            if self.follows_fit_:
                self.pool_.append(c.copy())
            self._decided()

    def _judged(self) -> Evidence:
        """The evidence a candidate is judged on: for a fitted candidate, its own episodes and
        those of the fitted candidates since the last deployment that the test left unsure
        (``pool_``), counted as its own. Each refit moves the model a little, and a candidate
        met by a few costly starts would otherwise start from nothing each time; a candidate
        the pooled test finds more likely worse than not empties the pool."""
        if not self.pool_ or not self.follows_fit_ or self.candidate_ is None:
            return self.evidence_
        n = len(self.deployed_)
        ev = Evidence(n, n, 1)
        ev.load_state_dict(self.evidence_.state_dict())
        pooled = {theta_key(t) for t in self.pool_}
        for i, z in enumerate(ev.Z):
            if theta_key(z) in pooled:
                ev.Z[i] = self.candidate_
        return ev

    def _decided(self) -> None:
        """The candidate is deployed or dropped."""
        self.candidate_ = None
        self.follows_fit_ = True
        self.decisions_ += 1
        self.waiting_ = 0

    def offer(self, theta: np.ndarray) -> None:
        """A candidate from elsewhere (the twin's tuning) on the deployed model, judged by that
        model's twin; the switch is not settled until it is decided."""
        if self.deployed_params_ is None:
            raise ValueError("offer needs a deployed identified model to judge the candidate on")
        self.candidate_ = np.array(theta, float)
        self.follows_fit_ = False
        self._twin(self.candidate_, self.deployed_params_)

    def settled(self) -> bool:
        """Whether identification is done (module docstring): after a deployment, when the fit
        brings no new candidate; after a drop, when it has brought none for ``min_runs``
        episodes; or, once an identified model is deployed, after ``MAX_DECISIONS``
        decisions."""
        if self.candidate_ is not None and not self.follows_fit_:
            return False  # an offered candidate is decided first
        if self.decisions_ >= MAX_DECISIONS and self.deployed_params_ is not None:
            return True
        if self.decisions_ == 0 or self.candidate_ is not None:
            return False
        return self.deployed_params_ is not None or self.waiting_ >= self.policy.min_runs

    def _propose_candidate(self, refresh: bool = False) -> None:
        """A candidate with the fitted model when the fit beats the nominal model on held-out
        transitions and has moved away from the deployed model (and from the last candidate);
        ``refresh``: in place of the candidate, which has not run yet. ``RESOLUTION`` holds for
        the deployed model and the candidate, not for a dropped one: on noise-free data any
        refit moves the fit, and a model dropped on unlucky episodes is tried again."""
        fit = self.identification_
        if fit is None or not fit.better:
            return
        plain = np.maximum(fit.std, 1e-12)
        live = np.maximum(plain, RESOLUTION * np.abs(fit.estimate))  # the models in use
        refs = [(self.fit.estimate_of(self.deployed_), live)]
        if self.tried_ is not None:  # the candidate (refresh), or the last one, dropped or not
            refs.append((self.tried_, live if refresh else plain))
        for ref, std in refs:
            if ref is not None and np.all(np.abs(fit.estimate - ref) <= MOVED * std):
                return
        # (refresh: the old candidate never ran, so the evidence holds nothing of it)
        self.candidate_ = self.fit.theta_with(self.deployed_, fit.estimate)
        self.tried_ = fit.estimate.copy()
        self._twin(self.candidate_, fit.params)

    def _twin(self, theta: np.ndarray, params: np.ndarray) -> None:
        """The candidate ``theta`` with the identified model ``params``: a fitted candidate's
        start covariate (random starts: the tests of a cycle are paired), an offered one's
        twin (module docstring)."""
        self.twin_ = (theta.copy(), np.asarray(params, float).copy())
        self._judge()
        if self.start_costs is None or not isinstance(self.policy, RandomEvidence):
            return
        if len(self.evidence_):
            nan = np.full(self.fit.system.nx, np.nan)  # an unknown initial state: no covariate
            x0s = np.array([nan if r is None else r.x0 for r in self.evidence_.replays])
            self.evidence_.start_costs = np.asarray(self.start_costs(x0s, *self.twin_), float)

    def _judge(self) -> None:
        """The evidence policy's judge: an offered candidate's the deployed model's twin, a
        fitted candidate's the plain tests (module docstring)."""
        offered = self.candidate_ is not None and not self.follows_fit_
        params = self.deployed_params_
        self.policy.twin = self.twin(params) if offered and params is not None else None

    def twin(self, params: np.ndarray) -> Twin | None:
        """The twin of the model ``params``, or None without the loop's closed loops."""
        if self.start_costs is None:
            return None
        return Twin.make(self.fit.system, params, self.start_costs, self.seed)

    def start_model(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The start covariate's controller and model (None: the learner's theta0 on the MPC's
        nominal model)."""
        if self.twin_ is None or not isinstance(self.policy, RandomEvidence):
            return None
        return self.twin_[0].copy(), self.twin_[1].copy()

    def next_theta(self) -> tuple[str, np.ndarray]:
        """The theta of the next episode and its kind: the candidate or the deployed theta as
        the evidence rule asks, else the deployed theta."""
        check = self.policy.next_check(self.evidence_, self.deployed_, self.candidate_)
        if check is not None:
            return check
        return "deployed", self.deployed_.copy()

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """Transitions, evidence, deployed theta, candidate and the last fit."""
        ident = self.identification_
        return {
            "transitions": self.transitions_.state_dict(),
            "evidence": self.evidence_.state_dict(),
            "deployed": self.deployed_.copy(),
            "candidate": None if self.candidate_ is None else self.candidate_.copy(),
            "tried": None if self.tried_ is None else self.tried_.copy(),
            "follows_fit": self.follows_fit_,
            "decisions": self.decisions_,
            "waiting": self.waiting_,
            "pool": [t.copy() for t in self.pool_],
            "identification": None if ident is None else asdict(ident),
            "twin": None if self.twin_ is None else (self.twin_[0].copy(), self.twin_[1].copy()),
            "deployed_params": self.deployed_params_,
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict` (a state of 1.0.0, which holds the last fit's estimate
        only, makes that fit again from it)."""
        self.transitions_ = Transitions.from_state_dict(state["transitions"])
        self.evidence_.load_state_dict(state["evidence"])
        self.deployed_ = np.array(state["deployed"], float)
        self.candidate_ = None if state["candidate"] is None else np.array(state["candidate"])
        self.tried_ = None if state["tried"] is None else np.array(state["tried"], float)
        self.follows_fit_ = bool(state.get("follows_fit", True))
        self.decisions_ = int(state["decisions"])
        # a 1.0.0 state: any decision had settled the switch (its rule)
        self.waiting_ = int(state.get("waiting", self.policy.min_runs))
        self.pool_ = [np.array(t, float) for t in state.get("pool", [])]
        if "x0s" in state:  # a state of 1.0: the initial states were the switch's
            self.evidence_.replays = replays_from_state(state["x0s"])
        twin = state["twin"]
        self.twin_ = None if twin is None else (np.array(twin[0], float), np.array(twin[1], float))
        dp = state["deployed_params"]
        self.deployed_params_ = None if dp is None else np.array(dp, float)
        self._judge()
        ident = state.get("identification")
        self.identification_ = None if ident is None else Identification(**ident)
        old = "identification" not in state and state["estimate"] is not None  # a 1.0.0 state
        if old and len(self.transitions_):
            self.identification_ = self.fit.fit(self.transitions_, start=state["estimate"])


class IdentifyLearner(Learner):
    """``identify``: the certainty-equivalent baseline (module docstring)."""

    name = "identify"
    options_class = IdentifyOptions

    def __init__(
        self,
        space: SearchSpace,
        theta0: np.ndarray,
        seed: int = 0,
        options: IdentifyOptions | None = None,
        *,
        starts: Starts | None = None,
        model_fit: ModelFit | None = None,
    ) -> None:
        super().__init__(space, theta0, seed, starts=starts)
        if model_fit is None:
            raise ValueError(
                "the identify learner needs the model to identify: run it in a study "
                "(it sets [system] identify) or give model_fit"
            )
        self.options = IdentifyOptions() if options is None else options
        self.switch_ = ModelSwitch(
            model_fit, self.theta0, self.starts, self.options.deploy, seed=self.seed
        )
        self.pending_: tuple[str, bytes] | None = None

    def propose(self) -> np.ndarray:
        """The candidate or the deployed theta."""
        kind, theta = self.switch_.next_theta()
        self.pending_ = (kind, theta_key(theta))
        return theta

    def observe(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """Refit on the episode's transitions and judge the candidate."""
        self.n_observed += 1
        kind = (
            self.pending_[0] if self.pending_ and self.pending_[1] == theta_key(theta) else "other"
        )
        self.pending_ = None
        self.switch_.observe(np.asarray(theta, float), result, kind)

    def incumbent(self) -> np.ndarray:
        """The deployed theta."""
        return self.switch_.deployed_.copy()

    def uses_start_cost(self) -> bool:
        """The evidence rule reads the episodes' start costs."""
        return True

    def start_model(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The start covariate's controller and model (:meth:`ModelSwitch.start_model`)."""
        return self.switch_.start_model()

    def use_start_costs(self, fn: StartCosts) -> None:
        """The loop's closed loops on a model: the start covariate and the twin."""
        self.switch_.start_costs = fn

    def identified(self) -> np.ndarray | None:
        """The current fit's estimate (None before a fit)."""
        ident = self.switch_.identification_
        return None if ident is None else ident.estimate.copy()

    def identification(self) -> Identification | None:
        """The switch's last fit (None before a fit)."""
        return self.switch_.identification_

    def state_dict(self) -> dict:
        """The base state and the switch's."""
        d = super().state_dict()
        d["switch"] = self.switch_.state_dict()
        d["pending"] = self.pending_
        return d

    def load_state_dict(self, state: dict) -> None:
        """Continue from a :meth:`state_dict`."""
        super().load_state_dict(state)
        self.switch_.load_state_dict(state["switch"])
        self.pending_ = state["pending"]


class IdentifyFirst(Learner):
    """A learner that runs the model switch first and then tunes from the deployed theta
    (module docstring). ``make_inner(theta0)`` builds the learner to tune with."""

    def __init__(
        self,
        make_inner: Callable[[np.ndarray], Learner],
        space: SearchSpace,
        theta0: np.ndarray,
        seed: int = 0,
        *,
        starts: Starts | None = None,
        model_fit: ModelFit,
        deploy: EvidenceDeploy | None = None,
    ) -> None:
        super().__init__(space, theta0, seed, starts=starts)
        self.make_inner = make_inner
        self.switch_ = ModelSwitch(
            model_fit, self.theta0, self.starts, deploy or EvidenceDeploy(), seed=self.seed
        )
        self.inner_: Learner | None = None
        self.name = make_inner(self.theta0).name
        self.pending_: tuple[str, bytes] | None = None
        self.history_: list[tuple[np.ndarray, EpisodeResult]] = []  # the switch's episodes
        self.start_costs: StartCosts | None = None
        self.twin_done_ = False  # the twin's tuning has run (or had nothing to tune)
        self.twin_: TwinResult | None = None

    def _tune_on_twin(self) -> None:
        """Tune the deployed theta on its identified model (:mod:`mpcmobo.learners.twin`) and
        offer the result to the switch if the twin finds it cheaper; nothing without a deployed
        identified model or the loop's closed loops on a model."""
        self.twin_done_ = True
        sw = self.switch_
        if sw.deployed_params_ is None or self.start_costs is None:
            return
        rng = np.random.default_rng(np.random.SeedSequence([self.seed, 11]))
        starts = np.array([sw.fit.system.sample_initial_state(rng) for _ in range(TWIN_STARTS)])
        self.twin_ = tune_on_twin(
            self.space, sw.deployed_, sw.deployed_params_, self.start_costs, starts, self.seed
        )
        if self.twin_.better:
            sw.offer(self.twin_.theta)

    def _tuning(self) -> Learner | None:
        """The learner that tunes, once the switch has settled and decided the twin's theta:
        built then, given the switch's episodes of the deployed theta if it takes them
        (``seed_with``), and judged by the deployed identified model's twin (``use_twin``)."""
        if self.inner_ is None and self.switch_.settled() and not self.twin_done_:
            self._tune_on_twin()
        if self.inner_ is None and self.switch_.settled():
            deployed = self.switch_.deployed_.copy()
            self.inner_ = self.make_inner(deployed)
            seed = getattr(self.inner_, "seed_with", None)
            own = [(t, r) for t, r in self.history_ if theta_key(t) == theta_key(deployed)]
            model = self.start_model()
            if seed is not None and own:
                if model is not None and self.start_costs is not None:  # their twin covariate
                    x0s = np.array([r.x0 for _, r in own])
                    costs = self.start_costs(x0s, *model)
                    own = [(t, replace(r, start_cost=float(c))) for (t, r), c in zip(own, costs)]
                seed(own)
            self.history_ = []
            params = self.switch_.deployed_params_
            twin = None if params is None else self.switch_.twin(params)
            use = getattr(self.inner_, "use_twin", None)
            if twin is not None and use is not None:
                use(twin)
        return self.inner_

    def start_model(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The start covariate's controller and model: the switch's while it runs, then the
        deployed theta on its identified model (None: the nominal model)."""
        if not self.switch_.settled():  # the switch stops when it settles: it stays so
            return self.switch_.start_model()
        params = self.switch_.deployed_params_
        if params is None or not isinstance(self.switch_.policy, RandomEvidence):
            return None
        return self.switch_.deployed_.copy(), params.copy()

    def use_start_costs(self, fn: StartCosts) -> None:
        """The loop's closed loops on a model: the twin's tuning, tests and covariate."""
        self.start_costs = fn
        self.switch_.start_costs = fn

    def propose(self) -> np.ndarray:
        """The switch's theta, then the tuning learner's proposal."""
        inner = self._tuning()
        if inner is not None:
            return inner.propose()
        kind, theta = self.switch_.next_theta()
        self.pending_ = (kind, theta_key(theta))
        return theta

    def observe(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """The switch's evidence and fit, or the tuning learner's observation."""
        self.n_observed += 1
        inner = self._tuning()
        if inner is not None:
            inner.observe(theta, result)
            return
        kind = (
            self.pending_[0] if self.pending_ and self.pending_[1] == theta_key(theta) else "other"
        )
        self.pending_ = None
        self.switch_.observe(np.asarray(theta, float), result, kind)
        self.history_.append((np.array(theta, float), result))

    def incumbent(self) -> np.ndarray:
        """The deployed theta: the switch's, then the tuning learner's."""
        inner = self._tuning()
        return self.switch_.deployed_.copy() if inner is None else inner.incumbent()

    def explores(self) -> bool:
        """The switch's episodes explore; then as the tuning learner says."""
        inner = self._tuning()
        return True if inner is None else inner.explores()

    def uses_start_cost(self) -> bool:
        """The switch reads the start costs; then as the tuning learner says."""
        inner = self._tuning()
        return True if inner is None else inner.uses_start_cost()

    def identified(self) -> np.ndarray | None:
        """The model identified for the deployed theta (the last fit while the switch runs)."""
        if self.inner_ is not None:
            return self.switch_.fit.estimate_of(self.switch_.deployed_)
        ident = self.switch_.identification_
        return None if ident is None else ident.estimate.copy()

    def identification(self) -> Identification | None:
        """The switch's last fit, the one the deployed model came from once it has settled
        (None before a fit)."""
        return self.switch_.identification_

    def state_dict(self) -> dict:
        """The base state, the switch's and the tuning learner's."""
        d = super().state_dict()
        d["switch"] = self.switch_.state_dict()
        d["inner"] = None if self.inner_ is None else self.inner_.state_dict()
        d["history"] = list(self.history_)
        d["pending"] = self.pending_
        d["twin_done"] = self.twin_done_
        d["twin"] = None if self.twin_ is None else asdict(self.twin_)
        return d

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue from a :meth:`state_dict`."""
        name = self.name
        state = dict(state, name=name)
        super().load_state_dict(state)
        self.switch_.load_state_dict(state["switch"])
        self.inner_ = None
        self.pending_ = state["pending"]
        self.history_ = [(np.array(t, float), r) for t, r in state["history"]]
        # a state from before the twin: a tuning learner had started without it
        self.twin_done_ = bool(state.get("twin_done", state["inner"] is not None))
        twin = state.get("twin")
        self.twin_ = None if twin is None else TwinResult(**twin)
        if state["inner"] is not None:
            inner = self._tuning()
            assert inner is not None  # the switch has decided (it saved a tuning learner)
            inner.load_state_dict(state["inner"])
