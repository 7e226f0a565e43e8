"""Bayesian-optimisation learners: BO on f1 (EI) and MPC-RL-MOBO on f1..f4 (EHVI).

Both search the unit cube of the declared search space (log coordinates for the weights), start
from theta0 (the imperfect MPC) plus a small seeded Sobol design, never fit a NaN objective, and
save and restore their whole state exactly.

Two choices help them work from single noisy episodes (each one a setting, measured in
``docs/benchmarks.md``):

* start effects: with cycled starts (``EpisodeResult.start_id >= 0``) the GP of each
  log-modelled cost carries one offset per start (``start_effects``, see
  :mod:`mpcmobo.bo.groups`), so candidates run on different starts are compared fairly;
* a risk-averse incumbent: the lowest ``m + kappa s`` of the modelled f1 (``incumbent_kappa``;
  0 gives the plain lowest predicted f1).

Issue 11's safe, contextual design is an option, not the default: measured at its settings in
session 5 (``docs/benchmarks.md``, "Safe by default? The GP learners, session 5") it kept
theta0 on most seeds. Switch it on with ``context = "x0"``, ``violation_budget = "auto"`` and
``deploy_confidence = 0.9`` (``benchmarks/configs/safe_context.toml``):

* ``context = "x0"``: the GPs model every outcome over ``(z, c)``, ``c`` the episode's
  initial state scaled to the initial-state box; acquisition and deployment use the
  expectation over ``n_contexts`` (8) fixed initial states (:mod:`mpcmobo.bo.context`). A
  learner built without the system's contexts (outside a study) models theta alone;
* ``violation_budget = "auto"`` (or a number: twice theta0's expected violation plus a floor
  from the state bounds) with ``safety_confidence`` (0.9): the per-episode plant violation is
  one more GP output; the EHVI / EI is weighted by the probability that the expected
  violation stays within the budget (BoTorch's ``constraints=``), a proposal whose
  ``safety_confidence`` quantile exceeds it is replaced by the best safe point of a trust
  region around the deployed theta (radius ``trust_radius sqrt(#safe points)`` in the unit
  cube), and the initial design fills the trust region around theta0 instead of the cube;
* ``deploy_confidence`` (e.g. 0.9) and ``deploy_min_runs`` (3): the deployed theta changes only to
  a theta that has been run on at least ``deploy_min_runs`` starts, did better than the
  deployed theta would have from the same start in *every* one of its episodes, is safe, and
  is better in expectation over the contexts with at least that posterior probability
  (:mod:`mpcmobo.learners.deploy`). A promising candidate with fewer runs is proposed again
  as a verification episode (``proposal_kinds_`` records "verify").

f3 under the context model (issue 11, item 4): the episode's f3 = max(0, V^c_l - V^c_{l-1})
is modelled, like f1, f2 and f4, as a function of ``(theta, x0_l)`` and integrated over the
fixed contexts, so candidates are compared at the same (expected) start of their own episode.
The previous episode (its start and theta) is not an input: it enters as noise, common in
distribution to all candidates. Modelling V^c itself over (theta, x0) and differencing the
expectations would remove that noise too; not done yet.

``search_radius`` (unset by default; session 6): search only the box ``z0 +- search_radius``
of the unit cube (``z0``: theta0's point), a learner's own :class:`SearchSpace` built by
:func:`local_space`. On ``lq`` every point of a Sobol design of the declared box is worse than
theta0 and the gain lies within 0.08 of ``z0``; on the CSTR the good theta is far from theta0,
so it is not a default (``docs/benchmarks.md``, "GP learners on `lq`").

``local_fit = k`` (unset by default; session 9, the safe design only): above ``k`` finite
episodes the GP is fitted, and the deployment rule, the safe points and the EHVI's front work,
on theta0's episodes and the episodes nearest to the deployed theta, ``k`` in all (TuRBO's
local GP, :func:`local_rows`). Replayed at 590 episodes it made an observation 3.4x cheaper
(k = 300) but not the search; its effect on learning is not measured
(``docs/benchmarks.md``, "The safe design's cost at large n").

``trust_region`` (``"auto"``, the default since session 7; ``"off"`` the search of the whole
box before it; :mod:`mpcmobo.bo.trust`, after TuRBO): the
acquisition (EI, EHVI, or the contextual one of the safe design) is maximised only in a box of
side ``L`` of the unit cube centred at the deployed theta (theta0 at first); the initial design
fills the first box around theta0. A proposal whose point becomes the deployed theta is a
success, any other a failure (the same rule for mobo: its deployed theta is chosen by f1);
``L`` doubles after ``success_tolerance`` successes in a row, halves after
``failure_tolerance`` (default ``max(4, d)``) failures in a row, up to ``length_max``, and
restarts at ``length_init`` below ``length_min``. ``"auto"`` takes the defaults of
:class:`~mpcmobo.bo.trust.TrustRegion` (``L`` 0.2 at first, at most 1.6); a table sets its
fields. With it on it replaces ``trust_radius`` in the safe design (the initial design and the
safe fallback use its box). Unlike ``search_radius`` the box moves with the deployed theta and
grows with evidence, so it can reach a good theta far from theta0 (the CSTR's). Measured in
``docs/benchmarks.md``, "A trust region for the GP learners (session 7)".

``deploy`` (session 8, issue 11 item 3; ``"auto"`` by default since session 10, below;
``"incumbent"``, the rule above, applied after every fit, the default before): ``"verified"`` keeps the search (EI / EHVI in the trust region) and changes
only which theta is deployed. A candidate (the observed theta with the best risk-averse
expected f1) replaces the deployed theta only when it has ``deploy_min_runs`` (default 2 here)
episodes of evidence, did better in every one of its episodes than the deployed theta from
the same start, and is better with posterior probability ``deploy_confidence`` (default 0.9
here) on joint GP samples (:meth:`DeployRule.decide <mpcmobo.learners.deploy.DeployRule.decide>`).
With cycled starts the evidence is like for like: only the candidate's episodes from a start
the deployed theta was run from count, compared with the deployed theta's observed cost from
that start, and a promising candidate is run again ("verify") when the next start is one the
deployed theta has, else the deployed theta is run from it ("baseline"); a candidate more
likely better than not but not yet convincing is run again up to ``deploy_max_runs`` (default
twice the minimum). With random starts nothing can be matched: the candidate's episodes are
compared with the GP's prediction of the deployed theta. Verification and baseline episodes,
and a search point that earns a verification, are neither successes nor failures of the trust
region; a candidate that becomes the deployed theta is a success. The first version of the
rule (the GP's probability and per-start offsets alone) regressed on ``lq``: with few
episodes per start the offsets are not identified (``docs/benchmarks.md``, "A deployment rule
that needs evidence").

``deploy = "auto"`` (the default since session 10): with cycled starts (known from the first
episode's ``start_id``) ``"verified"`` with ``deploy_paired = "cost"`` and ``deploy_min_runs``
the number of cycled starts (known after the cycle's first wrap): a candidate is deployed once
it has been run from every start of the cycle and its episodes are cheaper than the deployed
theta's own from the same starts on average, by a one-sided t-test with ``deploy_confidence``
(0.9); the GP picks the candidate (the best risk-averse expected f1) and needs only find it
more likely better than not (``deploy_model_confidence = 0.5``; unset it is
``deploy_confidence``, which held back candidates whose paired evidence was conclusive). With
random starts (since session 11) ``"verified"`` with ``deploy_paired = "cost"`` as well, but
unpaired: nothing can be matched, so the candidate's own episode costs are compared with the
deployed theta's own by a one-sided Welch t-test
(:func:`~mpcmobo.learners.deploy.unpaired_confidence`), each side with at least
``deploy_min_runs = 6`` episodes (up to 12); the deployed theta is run again ("baseline")
while it has fewer episodes than the candidate. Before session 11 random starts kept
``"incumbent"``, which regressed on 8 of 10 CSTR seeds; a checkpoint from then resumes with it.
Options set explicitly are kept, and the safe design (``context = "x0"``, a
``violation_budget`` or ``deploy_confidence``) keeps its own rule.
Measured in ``docs/benchmarks.md``, "The deployed theta on evidence from the whole cycle"
(mobo on 10 CSTR seeds: no regression but the seed-9 artefact of the evaluation starts, worst
seed 2.90 x J* against 9.93 under ``"incumbent"``).

``deploy_adjust = "start_cost"`` (the default since session 13; ``"none"`` the rule of session
11 above): under random starts every episode carries a covariate, ``EpisodeResult.start_cost``,
theta0's mean stage cost from the episode's start in a closed loop on the MPC's own model
(:func:`~mpcmobo.mpc.model_rollout`, no plant episode; the loop computes it because
:meth:`uses_start_cost` says so). Two things use it: the unpaired test compares the two thetas'
episode costs by the analysis of covariance on it
(:func:`~mpcmobo.learners.deploy.adjusted_confidence`) instead of Welch, and the GP, EI and EHVI
model f1 divided by it (:meth:`_model_Y`), the cost relative to how costly the start is. Cycled
starts are unchanged (their per-start offsets and paired tests already match the starts), and so
is the safe design (it models the start as a context). A checkpoint from before resumes with
``"none"``. Measured in ``docs/benchmarks.md``, "Random starts adjusted for their cost".

``deploy_screen`` (session 14; default ``"first"`` since session 17): with ``"relative"``,
under random starts and ``deploy_adjust = "start_cost"``, a candidate with fewer than
``deploy_min_runs`` episodes (or facing a deployed theta with fewer) is only screened on its
cost relative to its starts (:func:`~mpcmobo.learners.deploy.relative_screen`: run again or
dropped), and the test decides from ``deploy_min_runs`` a side. With ``"test"`` the start-adjusted test screens it
from its first episodes, and on two or three of them drops good candidates for good (an
intercept fitted to non-overlapping starts). The screen lets more candidates reach the test,
and on the CSTR more decisions meant one false deployment in 30 jobs: measured in
``docs/benchmarks.md``, "Screening candidates relative to their starts". ``deploy_screen =
"first"`` (session 16, the default since session 17) screens relatively only while a side has
a single episode, where the test has no degrees of freedom and falls back to the raw costs
(the start's luck), and leaves the rest to the test. A checkpoint resumes with the rule it was
started with (``"test"`` before session 17).

``deploy_baseline`` (session 16; default ``"early"`` since session 17, ``"verify"`` before, and
a checkpoint resumes with the rule it was started with): under random starts with
``"verify"`` the deployed theta is run again ("baseline") only to match a verified
candidate's evidence. With ``"early"`` it is also run, alternating with the search, until it has ``deploy_min_runs``
episodes, so that candidates are screened against evidence on it rather than against its one
episode from the design: on `lq` theta0's only episode came from a lucky start (cost 0.65 of
its start cost, against about 0.72 from most starts), no candidate looked better, and none
was ever run twice (session 15). Measured with ``deploy_screen = "first"``
(``benchmarks/configs/deploy_baseline_early.toml``) in ``docs/benchmarks.md``, "The deployed
theta's evidence first"; the pair is the default since session 17 (zero regressions on 10 CSTR
seeds of bo, mobo and hybrid and on `lq`, higher medians). Cycled starts never use either
option, so their records are unchanged.

``deploy_coverage`` (session 17; default ``"starts"`` since session 18, ``"episodes"`` before,
and a checkpoint resumes with the rule it was started with): under cycled starts
``"episodes"`` counted a candidate's matched *episodes* against ``deploy_min_runs``, so seven
episodes from four of the six starts were enough and the start carrying most of theta0's cost
could be missing from the evidence (28 of 61 deployments over 30 CSTR jobs, and the two real
regressions among them, bo and hybrid on seed 9). ``"starts"`` counts distinct matched starts
until the candidate has been run from every start of the cycle, then episodes as before.
Measured in ``docs/benchmarks.md``, "Deployed without every start of the cycle" and
"Every start of the cycle by default". Random starts are unchanged.

``trust_center`` and ``deploy_paired`` (session 9, issue 11; opt-in, defaults ``"deployed"`` and
``"every"``, the rules above): ``trust_center = "candidate"`` centres the trust region at the
deployment rule's best safe candidate while it is more likely better than the deployed theta
than not (a verification it survives is neutral for the box), so the search moves on before
the deployed theta may; ``deploy_paired = "mean"`` judges a candidate's own episodes against
the contextual model's prediction of the deployed theta at each episode's start by a one-sided
t-test on their mean (:func:`~mpcmobo.learners.deploy.paired_confidence`) instead of "better in
every episode" plus the pointwise dominance, and needs ``deploy_min_runs`` episodes of the
deployed theta itself (run as "baseline" episodes). Measured in ``docs/benchmarks.md``,
"Deploying sooner under the safe design" (``benchmarks/configs/safe_paired.toml``).

``deploy_paired = "cost"`` (session 10, issue 11; opt-in, for cycled starts): the same t-test
on the episode costs themselves, each of the candidate's episodes against the mean cost of the
deployed theta's own episodes from the same start (no model), so that the decision weighs the
starts as J does; with ``deploy = "verified"`` and ``deploy_min_runs`` = the number of cycled
starts, a candidate is deployed once it is better on average over the whole cycle with
``deploy_confidence``, where ``"every"`` needs it better from each start
(``benchmarks/configs/deploy_cycle_cost.toml``, and the default under cycled starts through
``deploy = "auto"``; ``docs/benchmarks.md``, "The deployed theta on evidence from the whole
cycle").

Three more options made things worse on the CSTR and were removed in the issue-10 clean-up
(their measurements stay in ``docs/benchmarks.md``): ``noise_floor`` (a lower bound on the GPs'
noise variance), ``confirm_runs`` (a new best point re-run before it became the incumbent) and
``replicate_every`` with ``max_replicates`` (periodic re-runs of the incumbent). Settings and
checkpoints that leave them at their old defaults still load; one switched on is refused.

Configuration and state are kept apart (as in scikit-learn): the constructor stores the options,
grouped into small objects (the GP in ``surrogate``, the acquisition search
:class:`~mpcmobo.bo.AcqfSearch` and :class:`~mpcmobo.bo.EHVIOptions`, the
:class:`IncumbentRule`); what is learned from episodes carries a trailing underscore (``Z_``,
``Y_``, ``grads_``, ``starts_``, ``ref_point_``, ...) and is what ``state_dict`` saves.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from scipy.stats import qmc

from mpcmobo.bo import (
    AcqfSearch,
    EHVIOptions,
    GPSurrogate,
    pareto_mask,
    propose_ehvi,
    propose_ei,
    reference_point,
)
from mpcmobo.bo.acquisition import Box
from mpcmobo.bo.context import (
    ContextSpec,
    expected_outcome_means,
    expected_outcome_samples,
    propose_context,
)
from mpcmobo.bo.trust import TrustState, trust_region_from_option
from mpcmobo.learners.base import EpisodeResult, Learner, check_choice
from mpcmobo.learners.deploy import (
    ADJUST_MODES,
    BASELINE_MODES,
    COVERAGE_MODES,
    PAIRED_MODES,
    SCREEN_MODES,
    DeployRule,
    adjusted_confidence,
    default_budget,
    paired_confidence,
    relative_screen,
    theta_key,
    unpaired_confidence,
)
from mpcmobo.systems.space import SearchSpace

OBJECTIVES = ("f1", "f2", "f3", "f4")
# hybrid_gradient (session 17, opt-in): the CDPG step of hybrid from the mean gradient of the
# incumbent's episodes, never to a theta already run ("mean"), or from the gradient of its
# nearest episode ("first", the default: while the incumbent stays, the same step again)
HYBRID_GRADIENTS = ("mean", "first")


class _DefaultStr(str):
    """A default value that knows it is one (``is`` tells an option left at its default from
    the same value given explicitly): see :data:`LEGACY_DEFAULTS`."""


class _DefaultInt(int):
    """As :class:`_DefaultStr`, for an integer."""


class _DefaultAny:
    """As :class:`_DefaultStr`, for an option that takes values of several types."""

    def __init__(self, value: Any) -> None:
        self.value = value

    def __repr__(self) -> str:
        return repr(self.value)


# issue 11's safe, contextual design stays behind options (context = "x0",
# violation_budget = "auto", deploy_confidence = 0.9): measured at these settings in session 5
# (docs/benchmarks.md) it kept theta0 on most seeds, so it is not the default. With it on,
# n_contexts is 8 and deploy_min_runs 3; options left at their defaults take their pre-session-5
# values when a checkpoint written before then is resumed (its learner state has no "design"
# key), so an old run continues with the settings it was started with
CONTEXT_DEFAULT = _DefaultStr("none")
N_CONTEXTS_DEFAULT = _DefaultInt(8)
BUDGET_DEFAULT = _DefaultAny(None)
DEPLOY_DEFAULT = _DefaultAny(None)
MIN_RUNS_DEFAULT = _DefaultInt(3)
# session 7: the trust region (mpcmobo.bo.trust) is the default of bo, mobo and hybrid (measured
# in docs/benchmarks.md, "Ten seeds in both start modes" and "A trust region for the GP
# learners"); a checkpoint whose learner state has no "trust_region" key was made without one
# and resumes without one when the option is left at its default
TRUST_DEFAULT = _DefaultAny("auto")
# session 8 (issue 11 item 3): which rule deploys on the default path. "incumbent": the observed
# point with the best risk-averse f1 after every fit (IncumbentRule, the rule before); "verified":
# a candidate is deployed only after deploy_min_runs episodes and with P(better) >=
# deploy_confidence (DeployRule). A checkpoint whose learner state has no "deploy" key was made
# with "incumbent" and resumes with it when the option is left at its default
DEPLOY_MODES = ("incumbent", "verified", "auto")
# session 9 (issue 11): where the trust region is centred. "deployed": the deployed theta (the
# rule since session 7); "candidate": the deployment rule's best safe candidate while it is more
# likely better than the deployed theta than not (the deployed theta otherwise), so that the
# search moves on with the evidence before the deployed theta may (docs/benchmarks.md,
# "Deploying sooner under the safe design")
TRUST_CENTERS = ("deployed", "candidate")
# session 10: "auto", the default: with cycled starts "verified" over the whole cycle
# (deploy_min_runs = the number of cycled starts, known after the first wrap) judged on the mean
# episode cost (deploy_paired = "cost"); with random starts "incumbent" (until session 11,
# below). A checkpoint whose learner state has no "deploy_option" key resumes with the rule in
# its "deploy" key
DEPLOY_MODE_DEFAULT = _DefaultStr("auto")
CYCLE_UNKNOWN = 10**6  # deploy = "auto" before the first wrap: no candidate has the evidence
# session 11: with random starts "auto" is "verified" too, judged on the episode costs unpaired
# (deploy_paired = "cost": a Welch t-test of the candidate's own episodes against the deployed
# theta's), each side with at least this many episodes (deploy_min_runs left at its default).
# A learner state without the "random_rule" key was made before: with random starts it resumes
# with the rules of then ("auto": the incumbent rule; "cost": the model's prediction)
RANDOM_MIN_RUNS = 6
RANDOM_RULE = "welch"
PAIRED_DEFAULT = _DefaultStr("every")  # "cost" under deploy = "auto" with cycled starts
AUTO_MODEL_CONFIDENCE = 0.5  # ... and deploy_model_confidence when unset
VERIFIED_CONFIDENCE = 0.9  # deploy = "verified": deploy_confidence when left unset
VERIFIED_MIN_RUNS = 2  # ... deploy_min_runs when left at its default
VERIFIED_MAX_RUNS_FACTOR = 2  # ... deploy_max_runs when unset: this multiple of the min runs
LEGACY_DEFAULTS: dict[str, Any] = {
    "context": "none",
    "n_contexts": 16,
    "violation_budget": None,
    "deploy_confidence": None,
    "deploy_min_runs": 1,
}
DESIGN_VERSION = 2  # learner states of the safe-by-default design carry {"design": 2}


def _is_default(value: Any) -> bool:
    return isinstance(value, (_DefaultStr, _DefaultInt, _DefaultAny))


def _plain(value: Any) -> Any:
    """The value of a default marker (as a plain str/float/int), or the value itself."""
    if isinstance(value, _DefaultAny):
        return value.value
    for cls, base in ((_DefaultStr, str), (_DefaultInt, int)):
        if isinstance(value, cls):
            return base(value)
    return value


# options removed in the issue-10 clean-up, each with the value that switched it off
REMOVED_OPTIONS: dict[str, Any] = {
    "noise_floor": None,
    "confirm_runs": 1,
    "replicate_every": 0,
    "max_replicates": 3,
}


def refuse_removed(options: dict[str, Any]) -> None:
    """Accept the removed options at their old defaults (old settings files still load); raise
    for one switched on, and for a name that was never an option."""
    for key, value in options.items():
        if key not in REMOVED_OPTIONS:
            raise TypeError(f"unexpected learner option '{key}'")
        if value != REMOVED_OPTIONS[key]:
            raise ValueError(
                f"{key} = {value!r}: this option was removed in the issue-10 clean-up (it made "
                f"results worse, docs/benchmarks.md); delete it or set it to "
                f"{REMOVED_OPTIONS[key]!r}"
            )


def reduced_effort(options: EHVIOptions, search: AcqfSearch) -> tuple[EHVIOptions, AcqfSearch]:
    """Half the quasi-MC samples, restarts and raw samples of an EHVI search (at least 1
    each, and at least as many raw samples as restarts).

    On the CSTR's 600-observation data this makes a proposal 2.9x faster; over the first 50
    episodes of 10 seeds the halved search learned worse than the full one
    (``docs/benchmarks.md``, "EHVI effort"). The mobo learner therefore searches in full
    while data are few and switches after ``reduce_effort_after`` observations.
    """
    r = max(1, search.num_restarts // 2)
    return (
        replace(options, mc_samples=max(1, options.mc_samples // 2)),
        replace(search, num_restarts=r, raw_samples=max(r, search.raw_samples // 2)),
    )


def search_effort(
    n: int, options: EHVIOptions, search: AcqfSearch, reduce_effort_after: int | None
) -> tuple[EHVIOptions, AcqfSearch]:
    """The EHVI options and search of a proposal after ``n`` observations: as given, halved
    (:func:`reduced_effort`) from ``reduce_effort_after`` observations on (None: never)."""
    if reduce_effort_after is not None and n >= reduce_effort_after:
        return reduced_effort(options, search)
    return options, search


def _check_radius(radius: float | None) -> float | None:
    if radius is None:
        return None
    r = float(radius)
    if not (np.isfinite(r) and 0 < r <= 0.5):
        raise ValueError(f"search_radius must be in (0, 0.5] (unit cube) or unset, got {radius}")
    return r


def _check_local_fit(local_fit: int | None) -> int | None:
    if local_fit is None:
        return None
    if (
        isinstance(local_fit, bool)
        or not isinstance(local_fit, (int, np.integer))
        or local_fit < 20
    ):
        raise ValueError(f"local_fit must be an integer >= 20 or unset, got {local_fit!r}")
    return int(local_fit)


def local_rows(
    Z: np.ndarray, ok: np.ndarray, center: np.ndarray, keep: np.ndarray, k: int
) -> np.ndarray:
    """Mask of the rows of ``Z`` a local fit uses (option ``local_fit``, TuRBO's local GP):
    all finite rows (``ok``) while there are at most ``k``; else the finite rows in ``keep``
    (theta0's episodes) and, up to ``k`` in all, the finite rows nearest to ``center`` (the
    deployed theta; Euclidean in the unit cube, ties by row order)."""
    if np.count_nonzero(ok) <= k:
        return ok.copy()
    mask = ok & keep
    rest = np.flatnonzero(ok & ~keep)
    dist = np.linalg.norm(Z[rest] - center, axis=1)
    n_more = max(0, k - int(np.count_nonzero(mask)))
    mask[rest[np.argsort(dist, kind="stable")[:n_more]]] = True
    return mask


def local_space(space: SearchSpace, theta0: np.ndarray, radius: float) -> SearchSpace:
    """The box ``z0 +- radius`` of the unit cube of ``space`` (``z0`` theta0's point, clipped
    to the cube) as a search space of its own: same coordinates, log flags and fixed entries,
    bounds the sub-box's ends in theta. A learner built on it searches only near theta0, in a
    region that is the same fraction of every declared range (option ``search_radius``)."""
    z0 = space.to_unit(space.clip(np.asarray(theta0, dtype=float)))
    lo = space.from_unit(np.clip(z0 - radius, 0.0, 1.0), base=theta0)
    hi = space.from_unit(np.clip(z0 + radius, 0.0, 1.0), base=theta0)
    f = space.free
    return SearchSpace(
        space.names,
        np.where(f, lo, space.lower),
        np.where(f, hi, space.upper),
        space.log,
        space.fixed,
    )


@dataclass(frozen=True)
class IncumbentRule:
    """The deployed point: among the observed points whose posterior means are Pareto-optimal
    (for one objective: all observed points), the one with the lowest predicted f1, judged
    risk-aversely by ``m + kappa * s`` with ``m, s`` the posterior mean and standard deviation
    of the modelled f1 (log f1 for a log output; ``kappa = 0``: the lowest predicted mean)."""

    kappa: float = 1.0

    def __post_init__(self) -> None:
        if not np.isfinite(self.kappa) or self.kappa < 0:
            raise ValueError(f"incumbent_kappa must be a finite number >= 0, got {self.kappa}")

    def choose(self, surrogate: GPSurrogate, Z: np.ndarray) -> int:
        """Index of the incumbent among the rows of ``Z`` (finite observations)."""
        mt, st = surrogate.posterior_model_space(Z)
        mean, _ = surrogate.to_cost_space(mt, st)
        cand = np.flatnonzero(pareto_mask(mean)) if mean.shape[1] > 1 else np.arange(len(Z))
        score = -mt[:, 0] + self.kappa * st[:, 0]  # model space is maximised: -mt
        return int(cand[int(np.argmin(score[cand]))])


class _GPLearner(Learner):
    """Shared machinery: design, data, surrogate fit after each episode, incumbent.

    The keyword options are the flat ``[learner_options.<name>]`` keys of a settings file.
    """

    outputs: tuple[int, ...] = (0,)

    def __init__(
        self,
        space: SearchSpace,
        theta0: np.ndarray,
        seed: int = 0,
        *,
        n_init: int = 5,
        refit_every: int = 10,
        refit_fraction: float = 0.1,
        log_outcomes: tuple[bool, ...] | None = None,
        num_restarts: int = 4,
        raw_samples: int = 256,
        maxiter: int = 100,
        start_effects: bool = True,
        incumbent_kappa: float = 1.0,
        context: str = CONTEXT_DEFAULT,
        n_contexts: int = N_CONTEXTS_DEFAULT,
        violation_budget: float | str | None = BUDGET_DEFAULT,  # type: ignore[assignment]  # a marked default
        safety_confidence: float = 0.9,
        deploy_confidence: float | None = DEPLOY_DEFAULT,  # type: ignore[assignment]  # a marked default
        deploy_min_runs: int = MIN_RUNS_DEFAULT,
        trust_radius: float = 0.1,
        contexts: ContextSpec | None = None,
        search_radius: float | None = None,
        trust_region: Any = TRUST_DEFAULT,
        deploy: str = DEPLOY_MODE_DEFAULT,
        deploy_max_runs: int | None = None,
        deploy_model_confidence: float | None = None,
        local_fit: int | None = None,
        trust_center: str = "deployed",
        deploy_paired: str = PAIRED_DEFAULT,
        deploy_adjust: str = "start_cost",
        deploy_screen: str = "first",
        deploy_baseline: str = "early",
        deploy_coverage: str = "starts",
        **removed: Any,
    ) -> None:
        self.deploy_adjust = check_choice("deploy_adjust", deploy_adjust, ADJUST_MODES)
        self.deploy_screen = check_choice("deploy_screen", deploy_screen, SCREEN_MODES)
        self.deploy_baseline = check_choice("deploy_baseline", deploy_baseline, BASELINE_MODES)
        self.deploy_coverage = check_choice("deploy_coverage", deploy_coverage, COVERAGE_MODES)
        self.search_radius = _check_radius(search_radius)
        self.local_fit = _check_local_fit(local_fit)
        self.trust_center = check_choice("trust_center", trust_center, TRUST_CENTERS)
        self.deploy_paired = check_choice("deploy_paired", _plain(deploy_paired), PAIRED_MODES)
        self._paired_defaulted = _is_default(deploy_paired)
        check_choice("deploy", deploy, DEPLOY_MODES)
        if deploy_max_runs is not None and (
            isinstance(deploy_max_runs, bool)
            or not isinstance(deploy_max_runs, (int, np.integer))
            or deploy_max_runs < 1
        ):
            raise ValueError(
                f"deploy_max_runs must be an integer >= 1 or unset, got {deploy_max_runs!r}"
            )
        self._deploy_defaulted = _is_default(deploy)
        self._random_rule = RANDOM_RULE  # "legacy": a checkpoint from before session 11
        # the option as given, and the rule in force ("auto" resolves at the first episode)
        self.deploy_option = _plain(deploy)
        self.deploy = "incumbent" if self.deploy_option == "auto" else self.deploy_option
        self._max_runs = None if deploy_max_runs is None else int(deploy_max_runs)
        self._model_confidence = (
            None if deploy_model_confidence is None else float(deploy_model_confidence)
        )
        self._trust_defaulted = _is_default(trust_region)
        self.trust_region = trust_region_from_option(_plain(trust_region))
        if self.search_radius is not None:
            space = local_space(space, theta0, self.search_radius)
        super().__init__(space, theta0, seed)
        refuse_removed(removed)
        safe = {
            "context": context,
            "n_contexts": n_contexts,
            "violation_budget": violation_budget,
            "deploy_confidence": deploy_confidence,
            "deploy_min_runs": deploy_min_runs,
        }
        # the options left at their defaults (for resuming pre-session-5 checkpoints)
        self._defaulted = {k for k, v in safe.items() if _is_default(v)}
        self._safe_options = {k: _plain(v) for k, v in safe.items()}
        self._safety_confidence = safety_confidence
        self._trust_radius = trust_radius
        self._contexts_spec = contexts
        self._kappa = incumbent_kappa
        self._configure_safe(
            **self._safe_options,
            safety_confidence=safety_confidence,
            trust_radius=trust_radius,
            contexts=contexts,
            kappa=incumbent_kappa,
        )
        if self.local_fit is not None and not self.safe_mode:
            raise ValueError(
                "local_fit applies to the safe design only (context = 'x0', a "
                "violation_budget or deploy_confidence); unset it or switch the design on"
            )
        self.incumbent_rule = IncumbentRule(incumbent_kappa)
        if n_init < 1:
            raise ValueError(f"n_init must be at least 1, got {n_init}")
        self.n_init = int(n_init)
        self.search = AcqfSearch(num_restarts, raw_samples, maxiter)
        # per-start offsets on the log-modelled costs, used when episodes cycle through fixed
        # starts (EpisodeResult.start_id >= 0); see "Start effects" in mpcmobo.bo.surrogate
        self.start_effects = bool(start_effects)
        self._surrogate_args = (log_outcomes, refit_every, refit_fraction)
        self.surrogate = self._make_surrogate(*self._surrogate_args)
        self.design = self._initial_design()
        self._design_version: int | None = DESIGN_VERSION  # None: the legacy defaults
        self._init_state()

    def _use_legacy_defaults(self) -> None:
        """Resuming a checkpoint written before the safe design became the default: the
        options left at their defaults take their old values (:data:`LEGACY_DEFAULTS`)."""
        for key in self._defaulted:
            self._safe_options[key] = LEGACY_DEFAULTS[key]
        self._defaulted = set()
        self._design_version = None  # and its checkpoints say so, so that it resumes so again
        self._configure_safe(
            **self._safe_options,
            safety_confidence=self._safety_confidence,
            trust_radius=self._trust_radius,
            contexts=self._contexts_spec,
            kappa=self._kappa,
        )
        self.surrogate = self._make_surrogate(*self._surrogate_args)
        self.design = self._initial_design()

    def _configure_safe(
        self,
        context: str,
        n_contexts: int,
        violation_budget: float | str | None,
        deploy_confidence: float | None,
        deploy_min_runs: int,
        *,
        safety_confidence: float,
        trust_radius: float,
        contexts: ContextSpec | None,
        kappa: float,
    ) -> None:
        """The options of issue 11 (module :mod:`mpcmobo.bo.context`,
        :mod:`mpcmobo.learners.deploy`). ``violation_budget = "off"`` and
        ``deploy_confidence = 0`` switch the safety constraint and the deployment rule off
        (the values a settings file can write for "unset")."""
        if violation_budget == "off":
            violation_budget = None
        if deploy_confidence is not None and deploy_confidence == 0:
            deploy_confidence = None
        if context not in ("none", "x0"):
            raise ValueError(f"context must be 'none' or 'x0', got {context!r}")
        if context == "x0" and contexts is None:
            raise ValueError("context = 'x0' needs the system's contexts (ContextSpec)")
        if isinstance(violation_budget, str) and violation_budget != "auto":
            raise ValueError(
                f"violation_budget must be a number >= 0, 'auto' or 'off', got {violation_budget!r}"
            )
        if isinstance(violation_budget, (int, float)) and not (
            np.isfinite(violation_budget) and violation_budget >= 0
        ):
            raise ValueError(f"violation_budget must be >= 0, got {violation_budget}")
        if not 0 < trust_radius <= 1:
            raise ValueError(f"trust_radius must be in (0, 1], got {trust_radius}")
        verified = self.deploy == "verified"
        max_runs = self._max_runs
        if verified:  # the evidence rule on any path, with its own defaults
            if deploy_confidence is None:
                deploy_confidence = VERIFIED_CONFIDENCE
            if "deploy_min_runs" in self._defaulted:
                deploy_min_runs = VERIFIED_MIN_RUNS
            if max_runs is None:
                max_runs = VERIFIED_MAX_RUNS_FACTOR * int(deploy_min_runs)
        self.context = context
        self.context_spec = contexts
        self.contexts = contexts.sample(int(n_contexts)) if context == "x0" else np.zeros((1, 0))  # type: ignore[union-attr]  # checked above
        self.violation_budget = violation_budget
        self.deploy_rule = DeployRule(
            kappa=float(kappa),
            deploy_confidence=None if deploy_confidence is None else float(deploy_confidence),
            safety_confidence=float(safety_confidence),
            min_runs=int(deploy_min_runs),
            max_runs=max_runs,
            model_confidence=self._model_confidence,
            # deploy = "verified" judges "every" episode, or their mean "cost" when asked
            paired_mode=self.deploy_paired
            if not verified or self.deploy_paired == "cost"
            else "every",
        )
        self.trust_radius = float(trust_radius)
        # the issue-11 path (contextual expectation, safety, deployment rule) or the old one;
        # deploy = "verified" alone keeps the default search (EI / EHVI) and only changes
        # which theta is deployed
        self.safe_mode = (
            context == "x0"
            or violation_budget is not None
            or (deploy_confidence is not None and not verified)
        )

    @property
    def _dc(self) -> int:
        return self.contexts.shape[1]

    def _make_surrogate(
        self, log_outcomes: tuple[bool, ...] | None, refit_every: int, refit_fraction: float
    ) -> GPSurrogate:
        m = len(self.outputs)
        log = (True,) * m if log_outcomes is None else tuple(log_outcomes)
        if len(log) != m:
            raise ValueError(f"log_outcomes needs {m} entries, got {len(log)}")
        groups = log if self.start_effects else None
        if self.violation_budget is not None:  # the violation, modelled like a cost (log)
            log = (*log, True)
            groups = None if groups is None else (*groups, False)
            m += 1
        return GPSurrogate(
            m,
            refit_every=refit_every,
            refit_fraction=refit_fraction,
            log_outcomes=log,
            group_outputs=groups,
        )

    def _initial_design(self) -> np.ndarray:
        """theta0, then scrambled Sobol points (seeded): ``n_init`` rows in unit coordinates.
        With a violation budget the Sobol points fill the trust region of radius
        ``trust_radius`` around theta0 (safe exploration starts from theta0 outward); with
        ``trust_region`` on they fill its first box (side ``length_init``) around theta0."""
        z0 = self.space.to_unit(self.theta0)
        sob = qmc.Sobol(d=self.space.dim, scramble=True, seed=self.seed).random(
            max(1, 2 ** int(np.ceil(np.log2(max(1, self.n_init)))))
        )
        if self.trust_region is not None:  # the first trust region (it replaces trust_radius)
            lo, hi = self.trust_region.box(z0, self.trust_region.length_init)
            sob = lo + (hi - lo) * sob
        elif self.violation_budget is not None:
            sob = np.clip(z0 + self.trust_radius * (2 * sob - 1), 0, 1)
        return np.vstack([z0, sob])[: self.n_init]

    def _init_state(self) -> None:
        """No episode observed yet."""
        m = len(self.outputs)
        self.Z_ = np.zeros((0, self.space.dim))  # unit-cube points
        self.Y_ = np.zeros((0, m))  # modelled objectives (NaN rows kept, never fitted)
        self.grads_ = np.zeros((0, self.space.n_theta))  # CDPG gradients (non-finite: 0)
        self.starts_ = np.zeros(0, dtype=int)  # start index of each observation (-1: random)
        self.C_ = np.zeros((0, self._dc))  # contexts (scaled x0) of each observation
        self.V_ = np.zeros(0)  # plant violation of each observation
        self.S0_ = np.zeros(0)  # start cost (EpisodeResult.start_cost) of each observation
        self.budget_: float | None = (
            float(self.violation_budget)
            if isinstance(self.violation_budget, (int, float))
            else None
        )
        self._pre_fit_state: dict | None = None
        self._fitted = False
        self._incumbent_z = self.space.to_unit(self.theta0)
        self._pre_fit_incumbent = self._incumbent_z.copy()
        self._exact_theta0: bool | None = True  # see _theta
        self._verify_z: np.ndarray | None = None  # a candidate to run again (deploy_min_runs)
        # the deployment rule's promising candidate (trust_center = "candidate"), and the
        # centre of the trust region before the last fit (for the trust region's update)
        self._candidate_z: np.ndarray | None = None
        self._pre_fit_centre = self._incumbent_z.copy()
        # what each proposal was: "design", "search", "safe" (the trust-region fallback),
        # "verify" (a candidate run again before it may be deployed), "baseline" (deploy =
        # "verified": the deployed theta run from a start it lacks), "gradient" (hybrid)
        self.proposal_kinds_: list[str] = []
        # the trust region's length and counters (None: no trust region), and before the last fit
        self.trust_: TrustState | None = (
            None if self.trust_region is None else self.trust_region.start()
        )
        self._pre_fit_trust = self.trust_

    # -------------------------------------------------------------- data
    def _theta(self, z: np.ndarray) -> np.ndarray:
        # exactly theta0, not its round trip through z (issue 11, item 5: J_eval moved by 2.8%
        # on the CSTR under that 4e-12 change); a checkpoint written before this rule keeps the
        # rule it was made with (exact only in the safe design)
        exact = self.safe_mode if self._exact_theta0 is None else self._exact_theta0
        if exact and np.array_equal(z, self.space.to_unit(self.theta0)):
            return self.theta0.copy()
        return self.space.from_unit(z, base=self.theta0)

    def _finite(self) -> np.ndarray:
        return np.all(np.isfinite(self.Y_), axis=1)

    def observe(self, theta: np.ndarray, result: EpisodeResult) -> None:
        z = self.space.to_unit(self.space.clip(theta))
        y = np.asarray(result.objectives, dtype=float)[list(self.outputs)]
        g = np.asarray(result.grad, dtype=float)
        self.Z_ = np.vstack([self.Z_, z])
        self.Y_ = np.vstack([self.Y_, y])  # NaN rows stay in the log, never in the fit
        self.grads_ = np.vstack([self.grads_, np.where(np.isfinite(g), g, 0.0)])
        self.starts_ = np.append(self.starts_, int(result.start_id))
        self.C_ = np.vstack([self.C_, self._context_of(result)])
        self.V_ = np.append(self.V_, float(result.violation))
        self.S0_ = np.append(self.S0_, float(result.start_cost))
        self.n_observed += 1
        self._fit()

    def _adjusted(self) -> bool:
        """Whether the GP models f1 relative to the start (``deploy_adjust = "start_cost"``
        under random starts): see :meth:`_model_Y`."""
        return (
            self.deploy_adjust == "start_cost"
            and not self.safe_mode  # the safe design models the start itself (context = "x0")
            and len(self.starts_) > 0
            and not self._cycled()
        )

    def _model_Y(self) -> np.ndarray:
        """The objectives as the GP, EI and EHVI see them: ``Y_``, but under random starts with
        ``deploy_adjust = "start_cost"`` f1 divided by the episode's start cost (theta0's cost
        from that start on the MPC's own model), the cost relative to how costly the start
        is, so that the GP does not read start luck as a theta effect (on `lq` the ratio is
        nearly independent of the start). Rows without a usable start cost take the median
        of the others. With cycled starts the per-start offsets do this (``start_effects``)."""
        if not self._adjusted():
            return self.Y_
        s = self.S0_
        ok = np.isfinite(s) & (s > 0)
        if not np.any(ok):
            return self.Y_
        s = np.where(ok, s, np.median(s[ok]))
        Y = self.Y_.copy()
        Y[:, 0] = Y[:, 0] / s
        return Y

    def _context_of(self, result: EpisodeResult) -> np.ndarray:
        if self._dc == 0:
            return np.zeros((1, 0))
        if result.x0 is None:
            raise ValueError("context = 'x0' needs EpisodeResult.x0 (the initial state)")
        return self.context_spec.unit(result.x0)[None, :]  # type: ignore[union-attr]  # dc > 0: context x0

    def _fit_data(self) -> tuple[np.ndarray, np.ndarray]:
        """Inputs (z, c) and outputs (objectives, and the violation if constrained)."""
        X = np.hstack([self.Z_, self.C_])
        if self.violation_budget is None:
            return X, self.Y_
        # an unknown violation (NaN: not reported) does not cost the episode's objectives: it
        # counts as the largest violation seen so far (0 if none), pessimistically
        V = self.V_
        worst = float(np.max(V[np.isfinite(V)])) if np.any(np.isfinite(V)) else 0.0
        V = np.where(np.isfinite(V), V, worst)
        return X, np.hstack([self.Y_, V[:, None]])

    def _auto_budget(self) -> float:
        """``violation_budget = "auto"``: a multiple of theta0's expected violation over the
        contexts (posterior mean, from all episodes so far) plus the system's floor
        (:func:`~mpcmobo.learners.deploy.default_budget`)."""
        z0 = self.space.to_unit(self.theta0)[None, :]
        S = expected_outcome_samples(self.surrogate, z0, self.contexts, n_samples=128, seed=5)
        floor = 0.0 if self.context_spec is None else self.context_spec.violation_floor
        return default_budget(float(S[:, 0, -1].mean()), floor)

    def _safe_budget(self) -> float | None:
        return self.budget_ if self.violation_budget is not None else None

    def _apply_auto(self) -> None:
        """``deploy = "auto"``: once the first episode says how the starts come, cycled starts
        switch the learner to ``deploy = "verified"`` with ``deploy_paired = "cost"``,
        ``deploy_model_confidence = 0.5`` (with "cost") and ``deploy_min_runs`` the number of
        cycled starts, known after the first wrap (before it no candidate can have been
        matched on that many starts), each unless set; random starts the same with
        ``deploy_min_runs = RANDOM_MIN_RUNS`` and the costs compared unpaired (since session
        11; a checkpoint from before keeps the incumbent rule). The safe design
        (``context``, ``violation_budget`` or ``deploy_confidence`` set) keeps its own rule,
        measured without it."""
        if self.deploy_option != "auto" or not len(self.starts_):
            return
        if not self._cycled() and self._random_rule != RANDOM_RULE:
            return  # random starts, a checkpoint from before session 11: the incumbent rule
        if self.safe_mode and self.deploy != "verified":
            return  # the safe design (switched on by the user) keeps its own deployment rule
        changed = self.deploy != "verified"
        self.deploy = "verified"
        if self._paired_defaulted and self.deploy_paired != "cost":
            self.deploy_paired, changed = "cost", True
        if self._model_confidence is None and self.deploy_paired == "cost":
            # the paired cost evidence decides; the GP picks the candidate (P >= 0.5)
            self._model_confidence, changed = AUTO_MODEL_CONFIDENCE, True
        if changed:
            self._configure_safe(
                **self._safe_options,
                safety_confidence=self._safety_confidence,
                trust_radius=self._trust_radius,
                contexts=self._contexts_spec,
                kappa=self._kappa,
            )
        if "deploy_min_runs" not in self._defaulted:
            return
        if self._cycled():
            n = self._cycle_length()
            runs = CYCLE_UNKNOWN if n is None else n
        else:
            runs = RANDOM_MIN_RUNS
        if self.deploy_rule.min_runs != runs:
            cap = self._max_runs if self._max_runs is not None else VERIFIED_MAX_RUNS_FACTOR * runs
            self.deploy_rule = replace(self.deploy_rule, min_runs=runs, max_runs=cap)

    def _cycle_length(self) -> int | None:
        """The number of cycled starts once the cycle has wrapped (None before): the start ids
        run 0, 1, ..., n - 1, 0, ...; the first one not above its predecessor is the wrap (with
        one start, its second episode)."""
        wrapped = len(self.starts_) > 1 and bool(np.any(np.diff(self.starts_) <= 0))
        return int(self.starts_.max()) + 1 if wrapped else None

    def _fit(self) -> None:
        """Fit the GP(s) on the finite observations, choose the deployed theta, move the trust
        region; the pre-fit state makes resume exact."""
        self._apply_auto()
        self._pre_fit_state = self.surrogate.state_dict()
        self._pre_fit_incumbent = self._incumbent_z.copy()
        self._pre_fit_trust = self.trust_
        self._pre_fit_centre = self._trust_centre().copy()
        self._candidate_z = None
        self._fit_and_deploy()
        if self.trust_center == "candidate":
            self._update_trust_candidate(self._pre_fit_centre)
        else:
            self._update_trust(self._pre_fit_incumbent)

    def _trust_centre(self) -> np.ndarray:
        """The centre of the trust region: the deployed theta, or with ``trust_center =
        "candidate"`` the deployment rule's promising candidate when there is one."""
        if self.trust_center == "candidate" and self._candidate_z is not None:
            return self._candidate_z
        return self._incumbent_z

    def _update_trust_candidate(self, previous: np.ndarray) -> None:
        """``trust_center = "candidate"``: the trust region's step (TuRBO's rule on the model's
        evidence, not on one noisy episode). A success when the point just run became the
        centre (the new promising candidate, or the deployed theta); a verification episode
        of the centre after which it is still the centre is evidence gathered, neither
        success nor failure; anything else (a search point that is not the new best
        candidate, a verification that dropped its candidate) is a failure."""
        n = self.Z_.shape[0]
        if self.trust_region is None or self.trust_ is None or n <= self.n_init:
            return
        last = theta_key(self.Z_[-1])
        centre = theta_key(self._trust_centre())
        success = centre == last and theta_key(previous) != last
        kinds = self.proposal_kinds_
        if len(kinds) == n and kinds[-1] == "baseline":  # evidence on the deployed theta
            return
        if not success and centre == last:
            verified = kinds[-1] == "verify" if len(kinds) == n else False
            if verified or any(theta_key(z) == last for z in self.Z_[:-1]):
                return
        self.trust_ = self.trust_region.update(self.trust_, success, self.space.dim)

    def _update_trust(self, previous: np.ndarray) -> None:
        """One step of the trust region (:mod:`mpcmobo.bo.trust`) per observation after the
        initial design: a success when the point just run became the deployed theta (it was
        not before), a failure otherwise. The same rule for bo, mobo and hybrid: the box is
        centred at the deployed theta, which is chosen by f1 (the incumbent rule), so it
        moves and grows exactly when the deployed theta does; a point that only extends the
        Pareto front in f2..f4 does not move what is deployed."""
        n = self.Z_.shape[0]
        if self.trust_region is None or self.trust_ is None or n <= self.n_init:
            return
        last = theta_key(self.Z_[-1])
        success = theta_key(self._incumbent_z) == last and theta_key(previous) != last
        if self.deploy == "verified" and not success:
            # deploy = "verified": a verification episode (a theta run before) and a search
            # point that earned one are evidence being gathered, not failures of the box
            repeat = any(theta_key(z) == last for z in self.Z_[:-1])
            earned = self._verify_z is not None and theta_key(self._verify_z) == last
            if repeat or earned:
                return
        self.trust_ = self.trust_region.update(self.trust_, success, self.space.dim)

    def _trust_box(self) -> Box | None:
        """The current trust region (lower, upper) around the deployed theta, or None."""
        if self.trust_region is None or self.trust_ is None:
            return None
        return self.trust_region.box(self._trust_centre(), self.trust_.length)

    def _fit_and_deploy(self) -> None:
        if np.count_nonzero(self._finite()) < 2:
            self._fitted = False
            return
        if not self.safe_mode:
            self.surrogate.fit(self.Z_, self._model_Y(), groups=self.starts_)
            self._fitted = True
            Zf = self.Z_[self._finite()]
            if self.deploy == "verified":
                self._decide(Zf)
                return
            self._incumbent_z = Zf[self.incumbent_rule.choose(self.surrogate, Zf)].copy()
            return
        X, Y = self._fit_data()
        ok = self._fit_rows(np.all(np.isfinite(Y), axis=1))
        if np.count_nonzero(ok) < 2:
            self._fitted = False
            return
        self.surrogate.fit(X[ok], Y[ok], groups=self.starts_[ok])
        self._fitted = True
        if self.violation_budget == "auto":
            self.budget_ = self._auto_budget()
        self._decide(self.Z_[ok])

    def _fit_rows(self, ok: np.ndarray) -> np.ndarray:
        """The rows (mask) the safe design fits and decides on: the finite ones ``ok``, or with
        ``local_fit = k`` and more than k of them, theta0's episodes and the episodes nearest
        to the deployed theta, k in all (:func:`local_rows`)."""
        if self.local_fit is None:
            return ok
        keep = np.all(self.Z_ == self.space.to_unit(self.theta0), axis=1)
        return local_rows(self.Z_, ok, self._incumbent_z, keep, self.local_fit)

    def _decide(self, Z: np.ndarray) -> None:
        """The deployment rule (:class:`~mpcmobo.learners.deploy.DeployRule`) on the observed
        thetas ``Z``: the deployed theta, and a candidate to run again (verification)."""
        decision = self.deploy_rule.decide(
            self.surrogate,
            Z,
            self._incumbent_z,
            self.contexts,
            self._safe_budget(),
            seed=1234 + self.Z_.shape[0],
            runs=self._matched_runs if self._matched() else self._runs,
            paired=self._paired_cost
            if self.deploy_paired == "cost"
            else self._paired_verified
            if self.deploy == "verified"
            else self._paired_mean
            if self.deploy_paired == "mean"
            else self._paired_better,
        )
        self._incumbent_z = decision.deployed
        self._verify_z = decision.verify
        self._candidate_z = decision.candidate

    def _runs(self, z: np.ndarray) -> int:
        """Episodes run with the unit-cube theta ``z`` (finite outcomes only)."""
        return len(self._rows_of(z))

    def _paired_better(self, z: np.ndarray, current: np.ndarray) -> bool:
        """Like for like on ``z``'s own episodes: its observed f1 (model space, minus its
        start's offset) against the posterior mean of ``current`` at the same initial states;
        True when ``z`` did better in every one of those episodes (pessimistic: on the CSTR a
        theta can be far better than theta0 from two starts and catastrophic from a third). The GP's opinion of ``z``
        can be fooled by a few points; its observed episodes, compared at their own starts,
        are the evidence."""
        rows = self._rows_of(z)
        if not len(rows):
            return False
        t_obs = self.surrogate.to_model_space(self._fit_data()[1][rows])[:, 0]
        return self._beats_prediction(rows, t_obs, current)

    def _paired_mean(self, z: np.ndarray, current: np.ndarray) -> float:
        """``deploy_paired = "mean"``: the context-matched comparison of ``z``'s own episodes
        with the contextual model's prediction of ``current`` at each episode's initial state
        (model space, start offset removed), as the confidence that ``z`` is better on
        average (:func:`~mpcmobo.learners.deploy.paired_confidence`)."""
        rows = self._rows_of(z)
        if not len(rows):
            return 0.0
        t_obs = self.surrogate.to_model_space(self._fit_data()[1][rows])[:, 0]
        return paired_confidence(self._advantages(rows, t_obs, current))

    def _paired_cost(self, z: np.ndarray, current: np.ndarray) -> float:
        """``deploy_paired = "cost"``: each episode of ``z`` from a cycled start on which
        ``current`` was run too, against the mean cost of ``current``'s own episodes from that
        start, in the episode cost f1 itself (J(theta) = E_x0[f1] is a mean of costs, and on
        the CSTR a few starts carry it: a theta better from most starts in log cost can still
        be worse on average); the confidence that ``z`` is better on average
        (:func:`~mpcmobo.learners.deploy.paired_confidence` of the differences). Episodes from
        starts ``current`` has not been run from are not evidence; with none matched (random
        starts) the model-based check of ``deploy_paired = "mean"``."""
        rows = self._rows_of(z)
        own = self._rows_of(current)
        d = []
        for i in rows:
            s = int(self.starts_[i])
            same = [j for j in own if s >= 0 and int(self.starts_[j]) == s]
            if same:
                d.append(float(np.mean(self.Y_[same, 0])) - float(self.Y_[i, 0]))
        if not d:
            if self._unpaired_cost():  # random starts: the two thetas' own costs, unpaired
                if self.deploy_adjust == "start_cost":  # ... adjusted for their starts
                    # too few episodes a side for the test: screened (never deployed), if asked
                    screen = min(len(own), len(rows)) < self._screened_below()
                    judge = relative_screen if screen else adjusted_confidence
                    return judge(self.Y_[own, 0], self.Y_[rows, 0], self.S0_[own], self.S0_[rows])
                return unpaired_confidence(self.Y_[own, 0], self.Y_[rows, 0])
            return self._paired_mean(z, current) if len(rows) else 0.0
        return paired_confidence(np.asarray(d))

    def _screened_below(self) -> int:
        """``deploy_screen``'s reach: a candidate is screened relatively while a side has
        fewer episodes than this ("test": never; "first": one; "relative": ``deploy_min_runs``)."""
        return {"test": 0, "first": 2, "relative": self.deploy_rule.min_runs}[self.deploy_screen]

    def _unpaired_cost(self) -> bool:
        """``deploy_paired = "cost"`` with random starts (since session 11): a candidate's
        episode costs against the deployed theta's own, unpaired
        (:func:`~mpcmobo.learners.deploy.unpaired_confidence`), both sides run up to the
        candidate's evidence ("baseline" episodes of the deployed theta)."""
        return (
            self.deploy_paired == "cost" and self._random_rule == RANDOM_RULE and not self._cycled()
        )

    def _advantages(self, rows: np.ndarray, t_obs: np.ndarray, current: np.ndarray) -> np.ndarray:
        """Per episode ``rows`` (observed f1 in model space ``t_obs``): how much better it did
        than the posterior mean of ``current`` at its initial state (model space, maximised;
        start offset removed)."""
        t_obs = t_obs - self.surrogate._group_matrix(self.starts_[rows])[:, 0]
        Xc = np.hstack([np.repeat(current[None, :], len(rows), axis=0), self.C_[rows]])
        mt, _ = self.surrogate.posterior_model_space(Xc)
        return t_obs - mt[:, 0]

    def _beats_prediction(self, rows: np.ndarray, t_obs: np.ndarray, current: np.ndarray) -> bool:
        """True when every episode ``rows`` (observed f1 in model space ``t_obs``, minus its
        start's offset) did better than the posterior mean of ``current`` at its initial state."""
        return bool(np.all(self._advantages(rows, t_obs, current) > 0))  # model space: maximised

    def _rows_of(self, z: np.ndarray) -> np.ndarray:
        """Rows of the finite observations run with the unit-cube theta ``z``."""
        key = theta_key(z)
        return np.array(
            [i for i in np.flatnonzero(self._finite()) if theta_key(self.Z_[i]) == key], dtype=int
        )

    def _matched(self) -> bool:
        """Whether evidence is counted like for like, per cycled start (``deploy =
        "verified"`` or ``deploy_paired = "cost"``)."""
        return self.deploy == "verified" or self.deploy_paired == "cost"

    def _cycled(self) -> bool:
        """Whether the episodes cycle through fixed starts (``start_id >= 0``)."""
        return len(self.starts_) > 0 and bool(np.all(self.starts_ >= 0))

    def _matched_runs(self, z: np.ndarray) -> int:
        """``deploy = "verified"``'s evidence count: with cycled starts, the episodes of ``z``
        from starts on which the deployed theta was run too (like for like; with
        ``deploy_coverage = "starts"`` the number of distinct starts among them while it is below
        ``deploy_min_runs``, the cycle's length, so that a candidate must have been run from
        every start); with random starts (nothing to match), all its episodes."""
        rows = self._rows_of(z)
        if not self._cycled():
            return len(rows)
        own = self._deployed_starts()
        matched = [int(self.starts_[i]) for i in rows if int(self.starts_[i]) in own]
        covered = len(set(matched))
        if self.deploy_coverage == "starts" and covered < self.deploy_rule.min_runs:
            return covered  # not yet run from every start: short of deploy_min_runs
        return len(matched)  # episodes (the cap deploy_max_runs counts these)

    def _deployed_starts(self) -> set[int]:
        """The starts from which the deployed theta has been run."""
        return set(self.starts_[self._rows_of(self._incumbent_z)].tolist())

    def _next_start(self) -> int | None:
        """The start of the next episode under cycled starts (``episode mod n``: after the
        first wrap ``n`` is known, before it the next index), None with random starts."""
        if not self._cycled():
            return None
        last = int(self.starts_[-1])
        n = self._cycle_length()
        return (last + 1) % n if n is not None else last + 1

    def _verification(self) -> tuple[str, np.ndarray]:
        """The episode that gathers evidence on the candidate ``_verify_z``: the candidate
        itself, or (``deploy = "verified"``, cycled starts) the deployed theta when it has not
        yet been run from the next start, so that the candidate's episodes there can be
        compared like for like ("baseline")."""
        assert self._verify_z is not None
        if self._unpaired_cost():
            # random starts, unpaired costs: the deployed theta gets as many episodes as the
            # candidate (up to deploy_max_runs), so that both means rest on evidence
            own = self._runs(self._incumbent_z)
            if own < min(self._runs(self._verify_z), self.deploy_rule.run_cap):
                return "baseline", self._incumbent_z.copy()
            return "verify", self._verify_z
        if self.deploy_paired in ("mean", "cost") and self.deploy != "verified":
            # deploy_paired = "mean": the deployed theta's own episodes anchor the model's
            # prediction of it; it is run again while it has fewer than the candidate (and
            # than deploy_min_runs), alternating the evidence on both sides
            own = self._runs(self._incumbent_z)
            if own < min(self._runs(self._verify_z), self.deploy_rule.min_runs):
                return "baseline", self._incumbent_z.copy()
        nxt = self._next_start() if self._matched() else None
        if nxt is not None and nxt not in self._deployed_starts():
            return "baseline", self._incumbent_z.copy()
        return "verify", self._verify_z

    def _paired_verified(self, z: np.ndarray, current: np.ndarray) -> bool:
        """``deploy = "verified"``'s like-for-like check: each episode of ``z`` from a cycled
        start on which ``current`` was run too is compared with the mean of ``current``'s own
        observed episodes from that start (no model: the per-start offsets are poorly
        estimated from few episodes); the others with :meth:`_paired_better`'s prediction.
        True when ``z`` did better in every one of its episodes."""
        T = self.surrogate.to_model_space(self._fit_data()[1])[:, 0]  # maximised
        rows = self._rows_of(z)
        if not len(rows):
            return False
        own = self._rows_of(current)
        rest = []
        for i in rows:
            same = [j for j in own if self.starts_[i] >= 0 and self.starts_[j] == self.starts_[i]]
            if not same:
                rest.append(i)
            elif not T[i] > np.mean(T[same]):
                return False
        if not rest:
            return True
        return self._beats_prediction(np.array(rest), T[rest], current)

    def incumbent(self) -> np.ndarray:
        return self._theta(self._incumbent_z)

    def uses_start_cost(self) -> bool:
        """``deploy_adjust = "start_cost"`` (the default): under random starts the unpaired
        test adjusts the episode costs for their starts' covariate, and the GP models f1
        relative to it (:meth:`_model_Y`)."""
        return self.deploy_adjust == "start_cost"

    def _next_seed(self) -> int:
        return int(self.rng.integers(2**31 - 1))

    def propose(self) -> np.ndarray:
        n = self.Z_.shape[0]
        if n < self.n_init:
            return self._proposed("design", self.design[n])
        if not self._fitted:  # every observation so far failed: keep exploring the design
            u = self.rng.uniform(size=self.space.dim)
            box = self._trust_box()
            return self._proposed("design", u if box is None else box[0] + (box[1] - box[0]) * u)
        if self._verify_z is not None:
            return self._proposed(*self._verification())
        if self._early_baseline():
            return self._proposed("baseline", self._incumbent_z.copy())
        if self.safe_mode:
            return self._theta(self._acquire_safe(self._next_seed()))
        return self._proposed("search", self._acquire(self._next_seed()))

    def _early_baseline(self) -> bool:
        """``deploy_baseline = "early"`` (session 16): under random starts with the unpaired
        test, the deployed theta is run again, alternating with the search, until it has
        ``deploy_min_runs`` episodes, so that a candidate's first episodes are screened
        against evidence rather than against the deployed theta's single, luck-of-the-start
        episode."""
        if self.deploy_baseline != "early" or not self._unpaired_cost():
            return False
        kinds = self.proposal_kinds_
        if kinds and kinds[-1] == "baseline":  # alternate with the search
            return False
        return self._runs(self._incumbent_z) < self.deploy_rule.min_runs

    def _proposed(self, kind: str, z: np.ndarray) -> np.ndarray:
        """Record what the proposal is (``proposal_kinds_``) and return its theta."""
        self.proposal_kinds_.append(kind)
        return self._theta(z)

    @property
    def n_verifications(self) -> int:
        """Verification episodes run so far (candidates run again, ``deploy_min_runs``)."""
        return self.proposal_kinds_.count("verify")

    def _safe_points(self) -> np.ndarray:
        """The observed thetas (unit cube) the surrogate calls safe (all without a budget),
        always with theta0 (safe by assumption)."""
        if self.local_fit is not None:  # the thetas of the local fit (its training inputs)
            Z = np.unique(np.asarray(self.surrogate.train_X)[:, : self.space.dim], axis=0)
        else:
            X, Y = self._fit_data()
            ok = np.all(np.isfinite(Y), axis=1)
            Z = np.unique(self.Z_[ok], axis=0)
        z0 = self.space.to_unit(self.theta0)
        budget = self._safe_budget()
        if budget is None or len(Z) == 0:
            return np.unique(np.vstack([Z, z0]), axis=0)
        # the cheap, conservative first pass (posterior marginals, no sampling)
        _, U = expected_outcome_means(
            self.surrogate, Z, self.contexts, quantile=self.deploy_rule.safety_confidence
        )
        return np.unique(np.vstack([Z[U[:, -1] <= budget], z0]), axis=0)  # type: ignore[index]  # a quantile was asked

    def _acquire_safe(self, seed: int) -> np.ndarray:
        """Constrained (log) EHVI / EI of the expected outcomes over the contexts, then the
        safety filter on the candidate; an unsafe one is replaced by the best safe point of
        a trust region around the deployed theta (radius ``trust_radius sqrt(#safe)``)."""
        budget = self._safe_budget()
        X, _ = self._fit_data()
        safe = self._safe_points()
        n_obj = len(self.outputs)
        ref = None
        if n_obj > 1:
            ref = (
                self.ref_point_  # type: ignore[attr-defined]  # n_obj > 1: a MOBOLearner
                if self.ref_point_ is not None  # type: ignore[attr-defined]
                else reference_point(self.Y_[self._finite()], margin=self.ref_margin)  # type: ignore[attr-defined]
            )
        options, search = self._safe_effort()
        z = propose_context(
            self.surrogate,
            self.surrogate.train_X,  # type: ignore[arg-type]  # fitted by _fit_data
            self.contexts,
            n_objectives=n_obj,
            ref_point=ref,
            seed=seed,
            mc_samples=options,
            budget=budget,
            search=search,
            safe_points=safe,
            box=self._trust_box(),
        )
        if budget is None:
            self.proposal_kinds_.append("search")
            return z
        S = expected_outcome_samples(self.surrogate, z[None, :], self.contexts, seed=seed)
        if self.deploy_rule.safe(S, budget)[0]:
            self.proposal_kinds_.append("search")
            return z
        self.proposal_kinds_.append("safe")
        return self._trust_region_point(seed, len(safe), budget)

    def _safe_effort(self) -> tuple[int, AcqfSearch]:
        return 64, self.search

    def _trust_region_point(self, seed: int, n_safe: int, budget: float) -> np.ndarray:
        """The best safe point (lowest expected f1) of 128 Sobol points of the trust region:
        the ``trust_region`` box when on, else the cube of radius ``trust_radius sqrt(n_safe)``
        around the deployed theta."""
        center = self._trust_centre()
        sob = qmc.Sobol(d=self.space.dim, scramble=True, seed=seed).random(128)
        box = self._trust_box()
        if box is not None:  # the trust region replaces the radius trust_radius sqrt(#safe)
            cand = box[0] + (box[1] - box[0]) * sob
        else:
            radius = min(0.5, self.trust_radius * np.sqrt(max(1, n_safe)))
            cand = np.clip(center + radius * (2 * sob - 1), 0, 1)
        E, U = expected_outcome_means(
            self.surrogate, cand, self.contexts, quantile=self.deploy_rule.safety_confidence
        )
        ok = U[:, -1] <= budget  # type: ignore[index]  # conservative (expected_outcome_means)
        if not ok.any():
            return center.copy()
        score = np.where(ok, E[:, 0], np.inf)
        return cand[int(np.argmin(score))]

    def _acquire(self, seed: int) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    # -------------------------------------------------------------- state
    def state_dict(self) -> dict:
        d = super().state_dict()
        d.update(
            {
                "Z": self.Z_.copy(),
                "Y": self.Y_.copy(),
                "grads": self.grads_.copy(),
                "starts": self.starts_.copy(),
                "surrogate_pre_fit": self._pre_fit_state,
                "incumbent_z": self._incumbent_z.copy(),
                "incumbent_pre_fit": self._pre_fit_incumbent.copy(),
                "contexts_x0": self.C_.copy(),
                "violations": self.V_.copy(),
                "start_costs": self.S0_.copy(),
                "deploy_adjust": self.deploy_adjust,
                "deploy_screen": self.deploy_screen,
                "deploy_baseline": self.deploy_baseline,
                "deploy_coverage": self.deploy_coverage,
                "violation_budget": self.budget_,
                "design": self._design_version,
                "proposal_kinds": list(self.proposal_kinds_),
                "exact_theta0": self._exact_theta0,
                "trust_region": None if self.trust_ is None else self.trust_.to_dict(),
                "deploy": self.deploy,
                "deploy_option": self.deploy_option,
                "deploy_paired": self.deploy_paired,
                "random_rule": self._random_rule,
                "trust_pre_fit": None
                if self._pre_fit_trust is None
                else self._pre_fit_trust.to_dict(),
                "centre_pre_fit": self._pre_fit_centre.copy(),
            }
        )
        return d

    def load_state_dict(self, state: dict) -> None:
        self._random_rule = state.get("random_rule", "legacy")
        if self._deploy_defaulted:
            # the option left at its default: the run continues with the option it was made
            # with; a checkpoint from before "auto" (session 10) with its rule (no "deploy"
            # key: made before session 8, with the incumbent rule), and so does one written
            # after resuming such a checkpoint
            self.deploy_option = state.get("deploy_option", state.get("deploy", "incumbent"))
        if self._deploy_defaulted and state.get("deploy", "incumbent") != self.deploy:
            self.deploy = state.get("deploy", "incumbent")
            if self._paired_defaulted:
                self.deploy_paired = state.get("deploy_paired", "every")
            self._configure_safe(
                **self._safe_options,
                safety_confidence=self._safety_confidence,
                trust_radius=self._trust_radius,
                contexts=self._contexts_spec,
                kappa=self._kappa,
            )
        if state.get("design") is None and self._defaulted:
            self._use_legacy_defaults()  # a checkpoint from before the safe defaults
        if state.get("trust_region") is None and self._trust_defaulted and self.trust_region:
            # the run was made without a trust region (before session 7, or while "off" was
            # the default): it continues without one
            self.trust_region = None
            self.trust_ = self._pre_fit_trust = None
            self.design = self._initial_design()
        super().load_state_dict(state)
        self.proposal_kinds_ = list(state.get("proposal_kinds", []))
        self._exact_theta0 = state.get("exact_theta0")  # None: a checkpoint from before
        self.Z_, self.Y_ = np.array(state["Z"], float), np.array(state["Y"], float)
        self.grads_ = np.array(state["grads"], float)
        self.starts_ = np.array(state.get("starts", np.full(len(self.Z_), -1)), dtype=int)
        # checkpoints written before issue 11 have no contexts and violations
        self.C_ = np.array(state.get("contexts_x0", np.full((len(self.Z_), self._dc), 0.5)), float)
        self.C_ = self.C_.reshape(len(self.Z_), self._dc)
        self.V_ = np.array(state.get("violations", np.full(len(self.Z_), np.nan)), float)
        # a checkpoint from before session 13 has no start costs: it resumes unadjusted
        self.S0_ = np.array(state.get("start_costs", np.full(len(self.Z_), np.nan)), float)
        self.deploy_adjust = state.get("deploy_adjust", "none")
        self.deploy_screen = state.get("deploy_screen", "test")  # absent before session 14
        self.deploy_baseline = state.get("deploy_baseline", "verify")  # absent before session 16
        self.deploy_coverage = state.get("deploy_coverage", "episodes")  # absent before session 17
        b = state.get("violation_budget", self.budget_)
        self.budget_ = None if b is None else float(b)
        self._incumbent_z = np.array(state["incumbent_z"], float)
        self._pre_fit_incumbent = np.array(
            state.get("incumbent_pre_fit", state["incumbent_z"]), float
        )
        self._fitted = False
        if self.trust_region is not None:
            pre = state.get("trust_pre_fit")
            self.trust_ = self.trust_region.start() if pre is None else TrustState.from_dict(pre)
            self._pre_fit_trust = self.trust_
            if state["surrogate_pre_fit"] is None and state.get("trust_region") is not None:
                self.trust_ = TrustState.from_dict(state["trust_region"])
        centre = state.get("centre_pre_fit")
        if self.trust_center == "candidate" and centre is not None:
            # the centre before the last fit (the candidate then, or the deployed theta)
            self._candidate_z = np.array(centre, float)
        self._apply_auto()  # the cycle's length from the restored starts
        if state["surrogate_pre_fit"] is not None:
            # replay the last fit from the state it started from: same model, same counters
            self.surrogate.load_state_dict(state["surrogate_pre_fit"])
            self._incumbent_z = self._pre_fit_incumbent.copy()
            self._fit()


class BOLearner(_GPLearner):
    """Single-objective BO: a GP on f1 (eq. GP, mean_var) and log expected improvement (eq. EI)."""

    name = "bo"
    outputs = (0,)

    def _acquire(self, seed: int) -> np.ndarray:
        return propose_ei(
            self.surrogate,
            self.Z_,
            self._model_Y(),
            seed=seed,
            search=self.search,
            box=self._trust_box(),
        )


class MOBOLearner(_GPLearner):
    """MPC-RL-MOBO: one GP per objective f1..f4 and expected hypervolume improvement (eq. EHVI).

    The reference point is fixed once, from the initial design (its nadir plus ``ref_margin``
    times its range per objective, :func:`mpcmobo.bo.reference_point`), and never moves.
    ``hybrid_every = k > 0`` makes every k-th proposal a CDPG gradient step from the incumbent
    (by default the gradient observed in the incumbent's nearest episode, re-run while the
    incumbent stays; ``hybrid_gradient = "mean"``, session 17: the mean of the gradients of
    the incumbent's episodes, never to a theta already run), uniting BO's global search with
    the gradient's local refinement (remark of section 4).

    The EHVI search (``mc_samples`` quasi-MC samples, ``num_restarts`` L-BFGS-B restarts from
    the best of ``raw_samples`` random points) is halved once ``reduce_effort_after``
    observations are in (None: never), see :meth:`search_effort`. ``direct_samples = True``
    draws the quasi-MC samples straight from the posterior mean and standard deviation
    (:class:`~mpcmobo.bo.EHVIOptions`): a faster search whose records differ from the default's
    in their last digits, so it is an option until measured (``docs/benchmarks.md``).
    """

    name = "mobo"
    outputs = (0, 1, 2, 3)

    def __init__(
        self,
        space: SearchSpace,
        theta0: np.ndarray,
        seed: int = 0,
        *,
        ref_margin: float = 0.1,
        mc_samples: int = 64,
        max_baseline: int = 32,
        reduce_effort_after: int | None = 100,
        method: str = "logehvi",
        direct_samples: bool = False,
        hybrid_every: int = 0,
        hybrid_step: float = 0.05,
        hybrid_gradient: str = "first",
        log_outcomes: tuple[bool, ...] | None = (True, True, False, False),
        **options: Any,
    ) -> None:
        super().__init__(space, theta0, seed, log_outcomes=log_outcomes, **options)
        if reduce_effort_after is not None and reduce_effort_after < 0:
            raise ValueError(f"reduce_effort_after must be >= 0 or None, got {reduce_effort_after}")
        self.reduce_effort_after = reduce_effort_after
        if hybrid_every < 0:
            raise ValueError(f"hybrid_every must be >= 0, got {hybrid_every}")
        self.ref_margin = ref_margin
        self.ehvi = EHVIOptions(
            mc_samples=mc_samples,
            max_baseline=max_baseline,
            method=method,
            direct_samples=bool(direct_samples),
        )
        self.hybrid_every, self.hybrid_step = int(hybrid_every), float(hybrid_step)
        self.hybrid_gradient = check_choice("hybrid_gradient", hybrid_gradient, HYBRID_GRADIENTS)

    def _init_state(self) -> None:
        super()._init_state()
        self.ref_point_: np.ndarray | None = None
        self.n_proposals_ = 0

    def _fit(self) -> None:
        if self.ref_point_ is None and self.Z_.shape[0] >= self.n_init:
            ok = self._finite()
            if np.any(ok):
                self.ref_point_ = reference_point(self._model_Y()[ok], margin=self.ref_margin)
        super()._fit()

    def propose(self) -> np.ndarray:
        """The next theta: the GP proposal, or every ``hybrid_every``-th time a CDPG step from the
        incumbent."""
        self.n_proposals_ += 1
        if self._verify_z is None and self._hybrid_due():
            step = self._gradient_step()
            if step is not None:
                self.proposal_kinds_.append("gradient")
                return step
        return super().propose()

    def _hybrid_due(self) -> bool:
        """Every ``hybrid_every``-th proposal after the design, once a GP is fitted."""
        return (
            self.Z_.shape[0] >= self.n_init
            and self._fitted
            and self.hybrid_every > 0
            and self.n_proposals_ % self.hybrid_every == 0
        )

    def _gradient_step(self) -> np.ndarray | None:
        """A normalised CDPG step (eq. theta) from the incumbent, in unit coordinates.

        ``hybrid_gradient = "mean"``: the mean of the CDPG gradients observed in the
        incumbent's episodes (its estimate over starts), and a step to a theta already run is
        not taken again (None: the GP proposes instead; it is taken anew once the incumbent's
        evidence moves the mean). ``"first"`` (the default): the gradient of the incumbent's
        nearest episode, so while the incumbent stays, every ``hybrid_every``-th proposal
        re-runs the same step however bad its episodes were.
        """
        rows = [int(np.argmin(np.linalg.norm(self.Z_ - self._incumbent_z, axis=1)))]
        keys: list[bytes] = []  # "mean": the thetas run, as identities
        if self.hybrid_gradient == "mean":  # all the incumbent's episodes (else its nearest)
            keys = [theta_key(z) for z in self.Z_]
            own = theta_key(self._incumbent_z)
            rows = [i for i, k in enumerate(keys) if k == own] or rows
        G = self.grads_[rows]
        G = G[np.any(G != 0, axis=1)]  # episodes with a gradient (non-finite ones are 0)
        if not len(G):
            return None
        theta = self._theta(self._incumbent_z)
        gz = G.mean(axis=0)[self.space.free] * self.space.dtheta_dz(theta)
        norm = np.max(np.abs(gz))
        if not np.isfinite(norm) or norm == 0:
            return None
        lo, hi = self._trust_box() or (0.0, 1.0)  # a step stays in the trust region
        z = np.clip(self._incumbent_z - self.hybrid_step * gz / norm, lo, hi)
        if theta_key(z) in keys:  # "mean": a step already run is not taken again
            return None
        return self._theta(z)

    def search_effort(self, n: int) -> tuple[EHVIOptions, AcqfSearch]:
        """The EHVI options and search of this learner's proposal after ``n`` observations
        (:func:`search_effort`)."""
        return search_effort(n, self.ehvi, self.search, self.reduce_effort_after)

    def _safe_effort(self) -> tuple[int, AcqfSearch]:
        options, search = self.search_effort(self.Z_.shape[0])
        return options.mc_samples, search

    def _acquire(self, seed: int) -> np.ndarray:
        ref = self.ref_point_
        if ref is None:
            ref = reference_point(self._model_Y()[self._finite()], margin=self.ref_margin)
        options, search = self.search_effort(self.Z_.shape[0])
        return propose_ehvi(
            self.surrogate,
            self.Z_,
            self._model_Y(),
            ref,
            seed=seed,
            options=options,
            search=search,
            box=self._trust_box(),
        )

    def state_dict(self) -> dict:
        """The base state plus the reference point and the number of proposals."""
        d = super().state_dict()
        d["ref_point"] = None if self.ref_point_ is None else self.ref_point_.copy()
        d["n_proposals"] = self.n_proposals_
        d["hybrid_gradient"] = self.hybrid_gradient
        return d

    def load_state_dict(self, state: dict) -> None:
        """Continue from a :meth:`state_dict`."""
        self.ref_point_ = None if state["ref_point"] is None else np.array(state["ref_point"])
        self.n_proposals_ = int(state["n_proposals"])
        self.hybrid_gradient = state.get("hybrid_gradient", "first")  # absent before session 17
        super().load_state_dict(state)


class HybridLearner(MOBOLearner):
    """MOBO with every ``hybrid_every``-th proposal a CDPG step from the incumbent (default 3)."""

    name = "hybrid"

    def __init__(
        self,
        space: SearchSpace,
        theta0: np.ndarray,
        seed: int = 0,
        *,
        hybrid_every: int = 3,
        **options: Any,
    ) -> None:
        super().__init__(space, theta0, seed, hybrid_every=hybrid_every, **options)
