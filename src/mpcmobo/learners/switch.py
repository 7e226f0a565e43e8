"""The model switch: the deployed theta against the candidate that puts the identified model
into it, judged on the evidence of the plant's episodes (:class:`ModelSwitch`).

The model is refitted from every plant transition so far (:class:`~mpcmobo.identify.ModelFit`)
once the transitions have grown by ``REFIT_GROWTH``: after every episode for the first ten,
then ever more rarely. A candidate is made once the fit predicts held-out transitions better
than the nominal model, and until its first episode it follows the fit. It is deployed only on
the evidence of its own episodes against the deployed theta's (the GP learners' rule,
:func:`~mpcmobo.learners.deploy.evidence_policy`, with the learner's deployment options); one
the evidence does not support, or with a failed episode, is dropped (one left unsure lends its
episodes to the next: ``ModelSwitch._judged``). A new candidate comes whenever the fit moves
away from the deployed model by ``MOVED`` standard deviations and by ``RESOLUTION`` of a value
(noise-free data give standard deviations near zero), and from a dropped one by ``MOVED``.

The switch has settled once a deployed model has not been left behind by the fit; after a
dropped candidate, once no new one has come for a verification's worth of episodes
(``min_runs``; cycled starts: a cycle); or, once an identified model is deployed, after
``MAX_DECISIONS`` decisions (under structural mismatch the fit moves as data come in). A
candidate offered from elsewhere (the twin's tuning, :meth:`ModelSwitch.offer`) is judged by
the deployed model's twin. Where the exploration budget keeps it off the plant from a start
(refused there, or not paying for itself on that model), its episode simulated on that model,
its costs times the model's spread (``EpisodeResult.spread``), stands in for the plant episode
from that start (``"bounded"`` evidence: pessimistic by the model's own record); kept off
from more than ``BOUNDED_SHARE`` of a verification's starts (``min_runs``; cycled starts: the
cycle), it is dropped without a deployment (:meth:`ModelSwitch.kept_off`). A fitted candidate
the budget refuses from a start of the cycle without a simulation (the model's error too
large) has the budget's own bound there instead: the deployed theta's plant episode from that
start times the bound on the candidate's cost ratio (:meth:`ModelSwitch.refused`), else the
cycle's paired test, which needs every start, never decides it. Under
random starts a fitted candidate's tests adjust each episode's cost by the identified model's
prediction of it."""

from __future__ import annotations

from dataclasses import asdict

import numpy as np

from mpcmobo.identify import Identification, ModelFit, Transitions
from mpcmobo.learners.base import EpisodeResult, Starts
from mpcmobo.learners.deploy import RandomEvidence, evidence_policy
from mpcmobo.learners.evidence import BOUNDED, Evidence, theta_key
from mpcmobo.learners.options import EvidenceDeploy
from mpcmobo.learners.prediction import StartCosts, Twin

__all__ = ["BOUNDED_SHARE", "MAX_DECISIONS", "MOVED", "REFIT_GROWTH", "RESOLUTION", "ModelSwitch"]

MOVED = 2.0  # a new candidate once the fit moves this many standard deviations
RESOLUTION = 1e-3  # ... and by more than this fraction of a value (noise-free data: std ~ 0)
REFIT_GROWTH = 0.1  # a refit once the transitions have grown by 10% since the last fit
MAX_DECISIONS = 2  # identify-first tuning starts after this many decisions (a model deployed)
# the share of a verification's starts an offered candidate may be judged on by its bounded
# simulations; kept off the plant more often, it is dropped
BOUNDED_SHARE = 1 / 3


def _bounds(result: EpisodeResult) -> bool:
    """Whether ``result`` bounds a candidate's episode: finite costs (f1 and the stage cost, not
    f2..f4) and a finite ``spread`` of at least 1."""
    spread = float(result.spread)
    costs = np.isfinite(result.f1) and np.isfinite(result.stage_cost)
    return bool(costs and np.isfinite(spread) and spread >= 1)


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
        self.kept_off_ = 0  # episodes the offered candidate was simulated instead of run
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
            self.evidence_.append(
                theta,
                y,
                np.zeros(len(theta)),
                result.start_id,
                result.start_cost,
                kind,
                cost=result.stage_cost,
                replay=result.replay,
            )
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
        self.kept_off_ = 0

    def offer(self, theta: np.ndarray) -> None:
        """A candidate from elsewhere (the twin's tuning) on the deployed model, judged by that
        model's twin; the switch is not settled until it is decided."""
        if self.deployed_params_ is None:
            raise ValueError("offer needs a deployed identified model to judge the candidate on")
        self.candidate_ = np.array(theta, float)
        self.follows_fit_ = False
        self.kept_off_ = 0
        self._twin(self.candidate_, self.deployed_params_)

    def offered(self) -> bool:
        """Whether the candidate is an offered one (:meth:`offer`), not yet decided."""
        return self.candidate_ is not None and not self.follows_fit_

    def verifying(self) -> np.ndarray | None:
        """The candidate being judged (None: none)."""
        return None if self.candidate_ is None else self.candidate_.copy()

    def kept_off(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """The offered candidate, if ``theta`` is it, was simulated instead of run (``result``):
        the exploration budget refused it from this episode's start, or the deployed model,
        which it was tuned on, predicts that it does not pay back its excess. The simulation,
        its costs times ``result.spread``, stands in for its plant episode from that start
        (``"bounded"`` evidence), then the candidate is decided as after a plant episode;
        kept off from more than ``BOUNDED_SHARE`` of ``min_runs`` starts, or without a finite
        bound, it is dropped (module docstring)."""
        if not (self.offered() and theta_key(theta) == self._candidate_key()):
            return
        self.kept_off_ += 1
        if not _bounds(result) or self.kept_off_ > BOUNDED_SHARE * self.policy.min_runs:
            self._decided()
            return
        self._append_bounded(theta, result)

    def refused(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """The fitted candidate, if ``theta`` is it, was refused by the exploration budget from
        this episode's start under cycled starts, without a simulation (the model's error is too
        large for one): ``result`` is the deployed theta's plant episode from that start, its
        ``spread`` the budget's bound on the candidate's cost as a multiple of it. The bound
        stands in for the candidate's episode from that start (``"bounded"`` evidence), so that
        the cycle's paired test, which needs every start, decides; refused from more than
        ``BOUNDED_SHARE`` of its starts (of the cycle, or of its episodes once they are more),
        it is dropped. Random starts need no stand-in: their test counts episodes from any
        start."""
        c = self.candidate_
        if c is None or not self.follows_fit_ or not self.policy.paired:
            return
        if theta_key(theta) != theta_key(c) or not _bounds(result):
            return
        self.kept_off_ += 1
        asked = max(self.policy.min_runs, len(self.evidence_.rows_of(c)) + 1)
        if self.kept_off_ > BOUNDED_SHARE * asked:
            self._decided()
            return
        self._append_bounded(theta, result)

    def _append_bounded(self, theta: np.ndarray, result: EpisodeResult) -> None:
        """``result``'s costs times its ``spread`` as ``theta``'s bounded episode from its
        start; then the decision on the candidate."""
        spread = float(result.spread)
        self.evidence_.append(
            theta,
            np.array([result.f1 * spread]),
            np.zeros(len(theta)),
            result.start_id,
            result.start_cost,
            BOUNDED,
            cost=result.stage_cost * spread,
            replay=result.replay,
        )
        self.decide()

    def settled(self) -> bool:
        """Whether identification is done (module docstring): after a deployment, when the fit
        brings no new candidate; after a drop, when it has brought none for ``min_runs``
        episodes; or, once an identified model is deployed, after ``MAX_DECISIONS``
        decisions."""
        if self.offered():
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
        params = self.deployed_params_
        self.policy.twin = self.twin(params) if self.offered() and params is not None else None

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
            "kept_off": self.kept_off_,
            "pool": [t.copy() for t in self.pool_],
            "identification": None if ident is None else asdict(ident),
            "twin": None if self.twin_ is None else (self.twin_[0].copy(), self.twin_[1].copy()),
            "deployed_params": self.deployed_params_,
        }

    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`."""
        self.transitions_ = Transitions.from_state_dict(state["transitions"])
        self.evidence_.load_state_dict(state["evidence"])
        self.deployed_ = np.array(state["deployed"], float)
        self.candidate_ = None if state["candidate"] is None else np.array(state["candidate"])
        self.tried_ = None if state["tried"] is None else np.array(state["tried"], float)
        self.follows_fit_ = bool(state["follows_fit"])
        self.decisions_ = int(state["decisions"])
        self.waiting_ = int(state["waiting"])
        self.kept_off_ = int(state.get("kept_off", 0))  # saved before refusals were counted
        self.pool_ = [np.array(t, float) for t in state["pool"]]
        twin = state["twin"]
        self.twin_ = None if twin is None else (np.array(twin[0], float), np.array(twin[1], float))
        dp = state["deployed_params"]
        self.deployed_params_ = None if dp is None else np.array(dp, float)
        self._judge()
        ident = state["identification"]
        self.identification_ = None if ident is None else Identification(**ident)
