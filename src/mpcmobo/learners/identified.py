"""Identify first, then tune: the learners built on the model switch
(:class:`~mpcmobo.learners.switch.ModelSwitch`).

* :class:`IdentifyLearner` (``identify``): the switch alone, the certainty-equivalent
  baseline that a control engineer tries first.
* :class:`IdentifyFirst`: the switch until it has settled, then another learner (the inner
  learner, built once, with the deployed theta as its theta0). The registry builds it from the
  settings (:func:`~mpcmobo.learners.registry.make_learner` with a ``model_fit``), and the
  switch judges with the inner learner's deployment options. The step to tuning is taken in
  :meth:`IdentifyFirst.observe`, once the switch has settled: on an identified model, theta is
  first tuned on the twin, the closed loop on that model (:mod:`mpcmobo.learners.twin`,
  reported through :meth:`~mpcmobo.learners.base.Learner.use_progress`), and the twin's theta,
  if cheaper there, is the switch's last candidate, judged by that model's twin
  (:class:`~mpcmobo.learners.prediction.Twin`), as the inner learner's candidates are. The
  inner learner then starts with the switch's episodes of its theta0
  (:meth:`~mpcmobo.learners.base.Learner.seed_with`) and that twin
  (:meth:`~mpcmobo.learners.base.Learner.use_twin`); the candidates the exploration budget
  refuses reach it as episodes simulated on the identified model
  (:meth:`~mpcmobo.learners.base.Learner.observe_simulated`). The twin's theta itself, where
  the budget keeps it off the plant from a start (refused, or not paying for itself on that
  model), is judged there on its simulated episode made pessimistic by the model's spread;
  kept off from more than a third of a verification's starts, it is dropped
  (:meth:`~mpcmobo.learners.switch.ModelSwitch.kept_off`), and the inner learner starts from
  the deployed theta.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, replace

import numpy as np

from mpcmobo.identify import Identification, ModelFit
from mpcmobo.learners.base import EpisodeResult, Learner, Progress, Starts
from mpcmobo.learners.deploy import RandomEvidence
from mpcmobo.learners.evidence import theta_key
from mpcmobo.learners.options import EvidenceDeploy, IdentifyOptions
from mpcmobo.learners.prediction import StartCosts
from mpcmobo.learners.switch import ModelSwitch
from mpcmobo.learners.twin import TWIN_STARTS, TwinResult, tune_on_twin
from mpcmobo.systems.space import SearchSpace

__all__ = ["IdentifyFirst", "IdentifyLearner"]

# builds the inner learner of identify-first from its theta0 (the deployed theta)
InnerFactory = Callable[[np.ndarray], Learner]


class _SwitchRunner:
    """What both identifying learners do while the switch runs: propose its theta, remember
    the proposal's kind, hand it the episode."""

    def __init__(self, switch: ModelSwitch) -> None:
        self.switch = switch
        self.pending: tuple[str, bytes] | None = None

    def propose(self) -> np.ndarray:
        """The candidate or the deployed theta."""
        kind, theta = self.switch.next_theta()
        self.pending = (kind, theta_key(theta))
        return theta

    def observe(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """Refit on the episode's transitions and judge the candidate."""
        pending = self.pending
        kind = pending[0] if pending and pending[1] == theta_key(theta) else "other"
        self.pending = None
        self.switch.observe(np.asarray(theta, float), result, kind)


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
        self.runner_ = _SwitchRunner(self.switch_)

    def propose(self) -> np.ndarray:
        """The candidate or the deployed theta."""
        return self.runner_.propose()

    def observe(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """Refit on the episode's transitions and judge the candidate."""
        self.n_observed += 1
        self.runner_.observe(theta, result)

    def observe_refused(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """The switch's bound on its refused candidate
        (:meth:`~mpcmobo.learners.switch.ModelSwitch.refused`)."""
        self.switch_.refused(theta, result)

    def incumbent(self) -> np.ndarray:
        """The deployed theta."""
        return self.switch_.deployed_.copy()

    def verifying(self) -> np.ndarray | None:
        """The switch's candidate (the identified model's theta, or the twin's) while it
        judges one."""
        return self.switch_.verifying()

    def uses_start_cost(self) -> bool:
        """The evidence rule reads the episodes' start costs."""
        return True

    def start_model(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The start covariate's controller and model (:meth:`ModelSwitch.start_model`)."""
        return self.switch_.start_model()

    def use_start_costs(self, costs: StartCosts) -> None:
        """The loop's closed loops on a model: the start covariate and the twin."""
        self.switch_.start_costs = costs

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
        d["pending"] = self.runner_.pending
        return d

    def load_state_dict(self, state: dict) -> None:
        """Continue from a :meth:`state_dict`."""
        super().load_state_dict(state)
        self.switch_.load_state_dict(state["switch"])
        self.runner_.pending = state["pending"]


class IdentifyFirst(Learner):
    """The model switch first, then the inner learner ``inner(theta0)`` named ``name`` tunes
    from the deployed theta (module docstring); ``deploy``: the switch's deployment options
    (the inner learner's)."""

    def __init__(
        self,
        inner: InnerFactory,
        space: SearchSpace,
        theta0: np.ndarray,
        seed: int = 0,
        *,
        name: str,
        starts: Starts | None = None,
        model_fit: ModelFit,
        deploy: EvidenceDeploy,
    ) -> None:
        super().__init__(space, theta0, seed, starts=starts)
        self.name = name
        self.make_inner = inner
        self.switch_ = ModelSwitch(model_fit, self.theta0, self.starts, deploy, seed=self.seed)
        self.runner_ = _SwitchRunner(self.switch_)
        self.inner_: Learner | None = None
        self.history_: list[tuple[np.ndarray, EpisodeResult]] = []  # the switch's episodes
        self.start_costs: StartCosts | None = None
        self.twin_done_ = False  # the twin's tuning has run (or had nothing to tune)
        self.twin_: TwinResult | None = None

    # ------------------------------------------------------------------ the loop
    def propose(self) -> np.ndarray:
        """The switch's theta, then the inner learner's proposal."""
        if self.inner_ is not None:
            return self.inner_.propose()
        return self.runner_.propose()

    def observe(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """The switch's evidence and fit, or the inner learner's observation; once the switch
        has settled, the twin's tuning and the inner learner (module docstring)."""
        self.n_observed += 1
        if self.inner_ is not None:
            self.inner_.observe(theta, result)
            return
        self.runner_.observe(theta, result)
        self.history_.append((np.array(theta, float), result))
        self._advance()

    def learns_in_simulation(self) -> bool:
        """As the inner learner says, once it tunes; before, while the switch judges the
        twin's theta (its offered candidate): the switch learns from the plant alone, but
        drops that candidate where the budget finds it does not pay for itself."""
        if self.inner_ is not None:
            return self.inner_.learns_in_simulation()
        return self.switch_.offered()

    def observe_simulated(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """The inner learner's simulated observation; before it tunes, the switch's, of the
        twin's theta simulated instead of run (module docstring)."""
        if self.inner_ is not None:
            self.inner_.observe_simulated(theta, result)
        else:
            self.switch_.kept_off(theta, result)

    def observe_refused(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """The inner learner's, once it tunes; before, the switch's bound on its refused
        fitted candidate (:meth:`~mpcmobo.learners.switch.ModelSwitch.refused`)."""
        if self.inner_ is not None:
            self.inner_.observe_refused(theta, result)
        else:
            self.switch_.refused(theta, result)

    def _advance(self) -> None:
        """Once the switch has settled: the twin's tuning (once), and when the switch has
        decided its theta too, the inner learner."""
        if self.inner_ is not None or not self.switch_.settled():
            return
        if not self.twin_done_:
            self._tune_on_twin()
        if self.switch_.settled():
            self.inner_ = self._start_inner(seeded=True)

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
            self.space,
            sw.deployed_,
            sw.deployed_params_,
            self.start_costs,
            starts,
            self.seed,
            progress=self.progress,
        )
        if self.twin_.better:
            sw.offer(self.twin_.theta)

    def _start_inner(self, seeded: bool) -> Learner:
        """The inner learner from the deployed theta, judged by the deployed identified model's
        twin; ``seeded``: given the switch's episodes of the deployed theta (with the twin's
        start covariate, where there is one) — a learner about to load a state needs them
        not."""
        deployed = self.switch_.deployed_.copy()
        inner = self.make_inner(deployed)
        inner.use_progress(self.progress)
        if seeded:
            own = [(t, r) for t, r in self.history_ if theta_key(t) == theta_key(deployed)]
            model = self.start_model()
            if own and model is not None and self.start_costs is not None:
                x0s = np.array([r.x0 for _, r in own])
                costs = self.start_costs(x0s, *model)
                own = [(t, replace(r, start_cost=float(c))) for (t, r), c in zip(own, costs)]
            if own:
                inner.seed_with(own)
            self.history_ = []
        params = self.switch_.deployed_params_
        twin = None if params is None else self.switch_.twin(params)
        if twin is not None:
            inner.use_twin(twin)
        return inner

    # ------------------------------------------------------------------ queries
    def incumbent(self) -> np.ndarray:
        """The deployed theta: the switch's, then the inner learner's."""
        if self.inner_ is None:
            return self.switch_.deployed_.copy()
        return self.inner_.incumbent()

    def verifying(self) -> np.ndarray | None:
        """The switch's candidate, then the inner learner's."""
        if self.inner_ is None:
            return self.switch_.verifying()
        return self.inner_.verifying()

    def explores(self) -> bool:
        """The switch's episodes explore; then as the inner learner says."""
        return True if self.inner_ is None else self.inner_.explores()

    def uses_start_cost(self) -> bool:
        """The switch reads the start costs; then as the inner learner says."""
        return True if self.inner_ is None else self.inner_.uses_start_cost()

    def start_model(self) -> tuple[np.ndarray, np.ndarray] | None:
        """The start covariate's controller and model: the switch's while it runs, then the
        deployed theta on its identified model (None: the nominal model)."""
        if not self.switch_.settled():  # the switch stops when it settles: it stays so
            return self.switch_.start_model()
        params = self.switch_.deployed_params_
        if params is None or not isinstance(self.switch_.policy, RandomEvidence):
            return None
        return self.switch_.deployed_.copy(), params.copy()

    def judge_starts(self) -> np.ndarray | None:
        """The deployed identified model's twin's simulated starts while it judges: the twin's
        theta offered to the switch, then the inner learner's candidates (None before: the
        switch judges its fitted candidates on the plant's episodes)."""
        if self.inner_ is None and not self.switch_.offered():
            return None
        params = self.switch_.deployed_params_
        twin = None if params is None else self.switch_.twin(params)
        return None if twin is None else twin.starts.copy()

    def identified(self) -> np.ndarray | None:
        """The model of the deployed theta once it is not theta0's nominal model (an
        identified model deployed, or one the tuning learner moved); else the last fit, also
        after the switch gave up and the tuning learner tunes the nominal model (None before
        a fit)."""
        if self.inner_ is not None:
            fit = self.switch_.fit
            own = fit.estimate_of(self.switch_.deployed_)
            if not np.array_equal(own, fit.estimate_of(self.theta0)):
                return own
        ident = self.switch_.identification_
        return None if ident is None else ident.estimate.copy()

    def identification(self) -> Identification | None:
        """The switch's last fit, the one the deployed model came from once it has settled
        (None before a fit)."""
        return self.switch_.identification_

    # ------------------------------------------------------------------ services
    def use_start_costs(self, costs: StartCosts) -> None:
        """The loop's closed loops on a model: the twin's tuning, tests and covariate."""
        self.start_costs = costs
        self.switch_.start_costs = costs

    def use_progress(self, progress: Progress | None) -> None:
        """Report the twin's tuning (and the inner learner's long work) to ``progress``."""
        super().use_progress(progress)
        if self.inner_ is not None:
            self.inner_.use_progress(progress)

    # ------------------------------------------------------------------ state
    def state_dict(self) -> dict:
        """The base state, the switch's and the inner learner's."""
        d = super().state_dict()
        d["switch"] = self.switch_.state_dict()
        d["inner"] = None if self.inner_ is None else self.inner_.state_dict()
        d["history"] = list(self.history_)
        d["pending"] = self.runner_.pending
        d["twin_done"] = self.twin_done_
        d["twin"] = None if self.twin_ is None else asdict(self.twin_)
        return d

    def load_state_dict(self, state: dict) -> None:
        """Continue from a :meth:`state_dict`."""
        super().load_state_dict(state)
        self.switch_.load_state_dict(state["switch"])
        self.runner_.pending = state["pending"]
        self.history_ = [(np.array(t, float), r) for t, r in state["history"]]
        self.twin_done_ = bool(state["twin_done"])
        twin = state["twin"]
        self.twin_ = None if twin is None else TwinResult(**twin)
        self.inner_ = None
        if state["inner"] is not None:
            self.inner_ = self._start_inner(seeded=False)
            self.inner_.load_state_dict(state["inner"])
