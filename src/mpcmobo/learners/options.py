"""The options of every learner, as typed, frozen, validated objects.

A settings file's ``[learner_options.NAME]`` table maps one to one onto the learner's options
class (:data:`OPTIONS`): an unknown key or an invalid value is an error that names it. Each
field's docstring says what the option does and what it costs; ``mpcmobo run --help`` and the
configuration reference (``docs/configuration.md``) are generated from them. Options that belong
together are one nested table (``search``, ``trust_region``, ``deploy``, ``optimizer``), and a
policy that behaves differently is a variant of its table chosen by ``rule`` (written as the bare
string when the other fields keep their defaults: ``deploy = "incumbent"``).
"""

from __future__ import annotations

from typing import Annotated, Any, ClassVar, Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

__all__ = [
    "OPTIONS",
    "AdamStep",
    "BOOptions",
    "EvidenceDeploy",
    "HybridOptions",
    "IdentifyOptions",
    "IncumbentDeploy",
    "IterateDeploy",
    "MOBOOptions",
    "MPCRLOptions",
    "PlainStep",
    "SearchOptions",
    "EHVISearch",
    "TrustRegionOptions",
    "VerifiedDeploy",
]


class _Options(BaseModel):
    model_config = ConfigDict(
        extra="forbid",
        frozen=True,
        strict=True,
        allow_inf_nan=False,
        use_attribute_docstrings=True,
    )
    # the policy tables of the class and the rule each one defaults to (``_rule_table``)
    _rules: ClassVar[dict[str, str]] = {}

    @model_validator(mode="before")
    @classmethod
    def _shorthands(cls, data: Any) -> Any:
        if isinstance(data, dict):
            data = dict(data)
            for key, default in cls._rules.items():
                if key in data:
                    data[key] = _rule_table(data[key], default)
            if data.get("trust_region") is True:
                data["trust_region"] = {}
        return data


def _rule_table(value: Any, default: str) -> Any:
    """A policy table from its bare name (``"incumbent"`` -> ``{rule = "incumbent"}``), or a
    table without ``rule`` as the default policy's."""
    if isinstance(value, str):
        return {"rule": value}
    if isinstance(value, dict) and "rule" not in value:
        return {"rule": default, **value}
    return value


# ---------------------------------------------------------------------- the GP learners
class SearchOptions(_Options):
    """How the acquisition function is maximised over the trust region (BoTorch's
    ``optimize_acqf``: L-BFGS-B from the best of ``raw_samples`` random points)."""

    num_restarts: int = Field(4, ge=1, le=256)
    """L-BFGS-B restarts per proposal. More find a better maximum of the acquisition; each one
    adds a local optimisation to every proposal."""
    raw_samples: int = Field(256, ge=1, le=1_000_000)
    """Random points whose best ones start the restarts. More: a better start, at one
    acquisition evaluation each."""
    maxiter: int = Field(100, ge=1, le=100_000)
    """Iterations per L-BFGS-B restart (an upper bound on a proposal's time)."""


class EHVISearch(SearchOptions):
    """The EHVI search of ``mobo`` and ``hybrid``: the acquisition search plus its quasi-Monte
    Carlo samples, all halved once the data are many."""

    mc_samples: int = Field(64, ge=1, le=4096)
    """Quasi-Monte Carlo samples of the expected hypervolume improvement. More: a smoother,
    more exact acquisition, slower in proportion."""
    reduce_effort_after: int = Field(100, ge=0)
    """From this many episodes on, ``mc_samples``, ``num_restarts`` and ``raw_samples`` are
    halved (a proposal about 3x faster on 600 episodes; the full search learns better while
    data are few). Set it above the episode budget to search in full throughout."""


class TrustRegionOptions(_Options):
    """A box of the unit cube centred at the deployed theta in which the acquisition is
    maximised (after TuRBO): it doubles after ``success_tolerance`` proposals in a row that
    became the deployed theta, halves after ``failure_tolerance`` that did not, and restarts
    at ``length_init`` below ``length_min``. Lengths are sides in the unit cube of the search
    space, so the same fraction of every declared range."""

    length_init: float = Field(0.2, gt=0, le=2)
    """Side of the first box (the initial design fills it around theta0)."""
    length_min: float = Field(0.0125, gt=0, le=2)
    """Below this side the box restarts at ``length_init``."""
    length_max: float = Field(1.6, gt=0, le=2)
    """The largest side (1 or more: the whole cube)."""
    success_tolerance: int = Field(2, ge=1)
    """Successes in a row that double the side."""
    failure_tolerance: int = Field(0, ge=0)
    """Failures in a row that halve the side; 0: ``max(4, d)``, ``d`` the searched
    coordinates."""

    @model_validator(mode="after")
    def _ordered(self) -> TrustRegionOptions:
        if not self.length_min <= self.length_init <= self.length_max:
            raise ValueError(
                "needs length_min <= length_init <= length_max, got "
                f"{self.length_min}, {self.length_init}, {self.length_max}"
            )
        return self


class EvidenceDeploy(_Options):
    """Deploy a candidate only on the evidence of its own episodes against the deployed
    theta's. The GP picks the candidate (the observed theta with the lowest risk-averse
    predicted f1, more likely better than the deployed theta than not); the study's start mode
    picks the test. Cycled starts: the candidate is run from every start of the cycle and its
    episodes are compared with the deployed theta's from the same starts (paired t-test of the
    episode costs). Random starts: the two thetas' episode costs, adjusted for how costly each
    start is (analysis of covariance on theta0's cost from the start on the MPC's model),
    each side with at least ``min_runs`` episodes; the deployed theta is run again early so
    that it has them. A candidate more likely better than not but not yet convincing is run
    again, up to twice the evidence needed. Without identification's twin to judge, a
    candidate under random starts is judged once, on ``2 min_runs`` episodes: a few cheap
    starts in a row, which the GP picks candidates for, are luck the start covariate does
    not see."""

    rule: Literal["evidence"] = "evidence"
    confidence: float = Field(0.9, ge=0.5, lt=1)
    """Confidence of the one-sided test that the candidate is cheaper. Higher: fewer false
    deployments, more episodes before a true one."""
    min_runs: int = Field(6, ge=2, le=10_000)
    """Random starts only: episodes of each side before a candidate can be deployed, twice
    as many for the candidate without identification's twin (cycled starts need one episode
    from every start of the cycle). More: safer decisions, later."""


class IncumbentDeploy(_Options):
    """The paper's rule: after every fit, deploy the observed theta with the lowest
    risk-averse predicted f1 (``incumbent_kappa``), on the GP's word alone. Fast, and it can
    deploy a theta worse than theta0 on a lucky episode."""

    rule: Literal["incumbent"] = "incumbent"


GPDeploy = Annotated[EvidenceDeploy | IncumbentDeploy, Field(discriminator="rule")]


class BOOptions(_Options):
    """``bo``: one GP on f1 (log) and log expected improvement."""

    n_init: int = Field(5, ge=1, le=10_000)
    """Episodes of the initial design: theta0, then scrambled Sobol points in the first trust
    region. More: a broader first model, fewer episodes left for the search."""
    refit_every: int = Field(10, ge=1, le=100_000)
    """A full fit of the GP hyperparameters every this many episodes (and, above 100 episodes,
    after every 10% growth of the data); in between the GP is conditioned on the new data with
    the last hyperparameters. Lower: hyperparameters that follow the data, slower episodes."""
    incumbent_kappa: float = Field(1.0, ge=0, le=100)
    """Risk aversion of the candidate choice: the observed theta with the lowest
    ``mean + kappa * std`` of the modelled f1. 0: the lowest predicted mean."""
    search: SearchOptions = SearchOptions()
    """The acquisition search."""
    trust_region: TrustRegionOptions | Literal[False] = TrustRegionOptions()
    """The trust region, a table of its fields; ``false``: search the whole box."""
    deploy: GPDeploy = EvidenceDeploy()
    """Which theta is deployed: ``"evidence"`` (the default) or ``"incumbent"`` (the
    paper's)."""

    _rules: ClassVar[dict[str, str]] = {"deploy": "evidence"}


class MOBOOptions(BOOptions):
    """``mobo`` (MPC-RL-MOBO): one GP per objective f1..f4 and log expected hypervolume
    improvement."""

    search: EHVISearch = EHVISearch()
    """The EHVI search."""
    ref_margin: float = Field(0.1, ge=0, le=10)
    """The hypervolume's reference point: the initial design's worst value per objective plus
    this fraction of its range, fixed once. Larger: more of the front counts, including
    points much worse than theta0."""


class HybridOptions(MOBOOptions):
    """``hybrid``: ``mobo`` with every ``gradient_every``-th proposal a step of the compatible
    policy gradient (CDPG) from the deployed theta."""

    gradient_every: int = Field(3, ge=1, le=10_000)
    """Every this many proposals one is a CDPG step instead of the EHVI's point."""
    gradient_step: float = Field(0.05, gt=0, le=1)
    """Length of that step in the unit cube (the largest coordinate's move)."""


# ---------------------------------------------------------------------- MPC-RL
class AdamStep(_Options):
    """Adam on the CDPG gradient in the normalised coordinates of the search space (log
    coordinates for the weights): free of the units of theta and of the cost."""

    rule: Literal["adam"] = "adam"
    lr: float = Field(0.03, gt=0, le=10)
    """Step size in the unit cube per step."""
    max_step: float = Field(0.1, gt=0, le=10)
    """The largest step (its norm in the unit cube)."""


class PlainStep(_Options):
    """The paper's rule, ``theta <- theta - lr grad_theta J`` in theta itself, no clipping;
    the result is projected onto the search bounds."""

    rule: Literal["gd"] = "gd"
    lr: float = Field(0.003, gt=0, le=1e6)
    """Step size in theta's units per unit of the gradient (depends on the cost's scale)."""


class VerifiedDeploy(_Options):
    """Deploy a verified iterate: the first ``runs`` episodes run theta0; then, every
    ``every`` gradient steps, the iterate is frozen for a block of ``runs`` episodes without
    exploration noise and replaces the deployed theta only if its episodes are cheaper than
    the deployed theta's block with ``confidence`` (cycled starts: paired per start; random
    starts: adjusted for the starts' cost). A promising block is extended up to ``max_runs``
    episodes where that brings new starts; a confidently worse one sends the iterate back to
    the deployed theta."""

    rule: Literal["verified"] = "verified"
    confidence: float = Field(0.9, ge=0.5, lt=1)
    """Confidence of the one-sided test that the candidate is cheaper."""
    every: int = Field(12, ge=0, le=100_000)
    """Gradient steps between verification blocks (0: a block after every block)."""
    runs: int = Field(6, ge=2, le=10_000)
    """Episodes per verification block. More: surer decisions, fewer gradient steps."""
    max_runs: int = Field(12, ge=2, le=100_000)
    """Episodes a promising block may be extended to."""

    @model_validator(mode="after")
    def _cap(self) -> VerifiedDeploy:
        if self.max_runs < self.runs:
            raise ValueError(f"max_runs ({self.max_runs}) must be at least runs ({self.runs})")
        return self


class IterateDeploy(_Options):
    """The paper's rule: the iterate itself is deployed after every step."""

    rule: Literal["iterate"] = "iterate"


class MPCRLOptions(_Options):
    """``mpc-rl``: compatible deterministic policy gradient steps on theta (eq. theta)."""

    optimizer: Annotated[AdamStep | PlainStep, Field(discriminator="rule")] = AdamStep()
    """The step rule: ``"adam"`` (the default) or ``"gd"`` (the paper's plain step)."""
    deploy: Annotated[VerifiedDeploy | IterateDeploy, Field(discriminator="rule")] = (
        VerifiedDeploy()
    )
    """Which theta is deployed: ``"verified"`` (the default) or ``"iterate"`` (the
    paper's)."""

    _rules: ClassVar[dict[str, str]] = {"optimizer": "adam", "deploy": "verified"}


class IdentifyOptions(_Options):
    """``identify``: the MPC with the model identified from the plant's transitions and
    theta0's cost, deployed on the evidence of its own episodes (the certainty-equivalent
    baseline)."""

    deploy: EvidenceDeploy = EvidenceDeploy()
    """How an identified model is judged against the deployed one before it is deployed (the
    evidence rule of the GP learners)."""

    _rules: ClassVar[dict[str, str]] = {"deploy": "evidence"}


OPTIONS: dict[str, type[_Options]] = {
    "mpc-rl": MPCRLOptions,
    "bo": BOOptions,
    "mobo": MOBOOptions,
    "hybrid": HybridOptions,
    "identify": IdentifyOptions,
}
"""The options class of each built-in learner."""
