"""Identify first, then tune: the MPC's model fitted from the plant's transitions.

* :class:`IdentifyLearner` (``identify``): the model switch alone
  (:class:`~mpcmobo.learners.switch.ModelSwitch`), the certainty-equivalent baseline that a
  control engineer tries first.
* :class:`IdentifyFirst`: the switch until it has settled, then any other learner built with
  the deployed theta as its theta0. The switch has settled once a deployed model has not been
  left behind by the fit; after a drop, once no new candidate has come for a verification's
  worth of episodes (``min_runs``; cycled starts: a cycle); or, once an identified model is
  deployed, after ``MAX_DECISIONS`` decisions (under structural mismatch the fit moves as data
  come in; drops alone would leave the learners tuning the nominal model). Settled on an
  identified model, theta is tuned on the twin, the closed loop on that model
  (:mod:`mpcmobo.learners.twin`), and the twin's theta, if cheaper there, is the switch's last
  candidate, judged by that model's twin (:class:`~mpcmobo.learners.twin.Twin`), as the
  tuning learner's candidates are. Each time the transitions have doubled while it tunes, a
  fit that has moved is a candidate again (the learner's deployed theta with that model),
  judged with the learner waiting: deployed, the tuning starts again from it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, replace
from typing import Any

import numpy as np

from mpcmobo.identify import ModelFit
from mpcmobo.learners.base import EpisodeResult, Learner, Starts
from mpcmobo.learners.deploy import RandomEvidence
from mpcmobo.learners.evidence import theta_key
from mpcmobo.learners.options import EvidenceDeploy, IdentifyOptions
from mpcmobo.learners.switch import ModelSwitch
from mpcmobo.learners.twin import TWIN_STARTS, StartCosts, TwinResult, tune_on_twin
from mpcmobo.systems.space import SearchSpace

__all__ = ["IdentifyFirst", "IdentifyLearner"]


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
        # the tuning learner's start covariate (its deployed theta and model), while it tunes
        self.tuning_model_: tuple[np.ndarray, np.ndarray] | None = None
        self.tuning_from_: np.ndarray | None = None  # the tuning learner's theta0
        self.refit_: int | None = None  # a later refit is judged: the switch's decisions then
        self.refit_at_ = 0  # the transitions that make a later refit worth judging

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
        """The learner that tunes, once the switch has settled and decided the twin's theta
        (None while the switch judges a later refit)."""
        if self.refit_ is not None:
            return None
        if self.inner_ is None and self.switch_.settled() and not self.twin_done_:
            self._tune_on_twin()
        if self.inner_ is None and self.switch_.settled():
            self._start_tuning(seed=True)
        return self.inner_

    def _start_tuning(self, seed: bool, theta0: np.ndarray | None = None) -> None:
        """Build the tuning learner from the deployed theta (or ``theta0``, a resumed one's):
        given the switch's episodes of that theta if it takes them (``seed_with``, with
        ``seed``), and judged by the deployed identified model's twin (``use_twin``)."""
        sw = self.switch_
        deployed = sw.deployed_.copy() if theta0 is None else np.array(theta0, float)
        params = sw.deployed_params_
        self.inner_ = self.make_inner(deployed)
        self.tuning_from_ = deployed
        random = isinstance(sw.policy, RandomEvidence)
        model = None if params is None or not random else (deployed, params.copy())
        self.tuning_model_ = model
        take = getattr(self.inner_, "seed_with", None)
        own = [(t, r) for t, r in self.history_ if theta_key(t) == theta_key(deployed)]
        if seed and take is not None and own:
            if model is not None and self.start_costs is not None:  # their twin covariate
                x0s = np.array([r.x0 for _, r in own])
                costs = self.start_costs(x0s, *model)
                own = [(t, replace(r, start_cost=float(c))) for (t, r), c in zip(own, costs)]
            take(own)
        self.history_ = []
        self.refit_at_ = 2 * sw.model_decided_at_
        twin = None if params is None else sw.twin(params)
        use = getattr(self.inner_, "use_twin", None)
        if twin is not None and use is not None:
            use(twin)

    def _tuned(self, theta: np.ndarray, result: EpisodeResult, explored: bool) -> None:
        """While the learner tunes: the episode's transitions for the fit, and the episodes of
        its deployed theta (and of the theta just run, which may become it) that explored as
        the switch's do; once the transitions have doubled since the model was decided, a
        refit that has moved away from the deployed model is judged (:meth:`ModelSwitch.reopen`)
        with the learner waiting."""
        assert self.inner_ is not None
        sw = self.switch_
        sw.record(result, refit=False)
        deployed = self.inner_.incumbent()
        if explored:
            self.history_.append((np.array(theta, float), result))
        keep = {theta_key(deployed), theta_key(theta)}
        self.history_ = [(t, r) for t, r in self.history_ if theta_key(t) in keep]
        if len(sw.transitions_) < self.refit_at_:
            return
        self.refit_at_ = 2 * len(sw.transitions_)
        sw.refit()
        own = [(t, r) for t, r in self.history_ if theta_key(t) == theta_key(deployed)]
        last = [] if own and own[-1][1] is result else [(np.array(theta, float), result)]
        if sw.reopen(deployed, own + last):
            self.refit_ = sw.decisions_
            self.history_ = own

    def _refit_decided(self) -> None:
        """The later refit is decided: deployed, the tuning starts again from it; dropped, the
        learner goes on."""
        assert self.inner_ is not None
        sw = self.switch_
        self.refit_ = None
        self.refit_at_ = 2 * sw.model_decided_at_
        deployed = self.inner_.incumbent()
        if theta_key(sw.deployed_) == theta_key(deployed):
            self.history_ = [
                (t, r) for t, r in self.history_ if theta_key(t) == theta_key(deployed)
            ]
            return
        self.inner_, self.twin_done_, self.twin_, self.tuning_model_ = None, False, None, None

    def start_model(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The start covariate's controller and model: the switch's while it runs, then the
        deployed theta on its identified model (None: the nominal model)."""
        if self.inner_ is None or self.refit_ is not None:
            return self.switch_.start_model()
        return (
            None
            if self.tuning_model_ is None
            else (self.tuning_model_[0].copy(), self.tuning_model_[1].copy())
        )

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
            explored = inner.explores()  # as the episode ran: the proposal's
            inner.observe(theta, result)
            self._tuned(theta, result, explored)
            return
        kind = (
            self.pending_[0] if self.pending_ and self.pending_[1] == theta_key(theta) else "other"
        )
        self.pending_ = None
        self.switch_.observe(np.asarray(theta, float), result, kind)
        self.history_.append((np.array(theta, float), result))
        if self.refit_ is not None and self.switch_.decisions_ > self.refit_:
            self._refit_decided()

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
        if self.inner_ is not None and self.refit_ is None:
            return self.switch_.fit.estimate_of(self.switch_.deployed_)
        ident = self.switch_.identification_
        return None if ident is None else ident.estimate.copy()

    def state_dict(self) -> dict:
        """The base state, the switch's and the tuning learner's."""
        d = super().state_dict()
        d["switch"] = self.switch_.state_dict()
        d["inner"] = None if self.inner_ is None else self.inner_.state_dict()
        d["history"] = list(self.history_)
        d["pending"] = self.pending_
        d["twin_done"] = self.twin_done_
        d["twin"] = None if self.twin_ is None else asdict(self.twin_)
        d["tuning_from"] = self.tuning_from_
        d["tuning_model"] = self.tuning_model_
        d["refit"] = self.refit_
        d["refit_at"] = self.refit_at_
        return d

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Continue from a :meth:`state_dict`."""
        name = self.name
        state = dict(state, name=name)
        super().load_state_dict(state)
        self.switch_.load_state_dict(state["switch"])
        self.inner_, self.refit_, self.tuning_model_, self.tuning_from_ = None, None, None, None
        self.pending_ = state["pending"]
        # a state from before the twin: a tuning learner had started without it
        self.twin_done_ = bool(state.get("twin_done", state["inner"] is not None))
        twin = state.get("twin")
        self.twin_ = None if twin is None else TwinResult(**twin)
        if state["inner"] is not None:  # (a state before later refits: the switch's theta)
            self._start_tuning(seed=False, theta0=state.get("tuning_from"))
            assert self.inner_ is not None
            self.inner_.load_state_dict(state["inner"])
            if "tuning_model" in state:
                model = state["tuning_model"]
                self.tuning_model_ = (
                    None
                    if model is None
                    else (np.array(model[0], float), np.array(model[1], float))
                )
        self.history_ = [(np.array(t, float), r) for t, r in state["history"]]
        self.refit_ = state.get("refit")
        self.refit_at_ = int(state.get("refit_at", 2 * len(self.switch_.transitions_)))
