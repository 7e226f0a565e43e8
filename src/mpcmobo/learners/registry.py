"""Learners by name: one :class:`LearnerSpec` per learner carries everything the package knows
about it (class, options class, label and colour in the figures, scheduling cost, whether the
paper runs it). Adding a learner is one entry in ``LEARNER_SPECS``.

The built-in learners' classes are named by ``"module:Class"`` and imported when a learner is
built: reading the names, labels and options (the settings, the command line) imports neither
torch nor BoTorch."""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from pydantic import BaseModel, ValidationError

from mpcmobo.learners.options import (
    BOOptions,
    EvidenceDeploy,
    HybridOptions,
    IdentifyOptions,
    MOBOOptions,
    MPCRLOptions,
    VerifiedDeploy,
)
from mpcmobo.systems.space import SearchSpace

if TYPE_CHECKING:
    from mpcmobo.identify import ModelFit
    from mpcmobo.learners.base import Learner, Starts

__all__ = [
    "LEARNERS",
    "LEARNER_SPECS",
    "LearnerOptionError",
    "LearnerSpec",
    "describe_options",
    "learner_options",
    "make_learner",
    "option_fields",
    "register_learner",
    "switch_deploy",
    "validate_options",
]


@dataclass(frozen=True)
class LearnerSpec:
    """One learner: its settings name, class (or ``"module:Class"``, imported when first
    needed: :meth:`learner_class`), options class (None: it takes no options), figure label
    and colour, its relative cost per episode (only to start the slowest jobs first: the EHVI
    learners spend the most per episode, MPC-RL the least), and whether the paper's study runs
    it (the default ``learners`` of the settings)."""

    name: str
    cls: type[Learner] | str
    label: str
    color: str
    job_cost: int
    in_paper: bool
    options: type[BaseModel] | None = None

    def learner_class(self) -> type[Learner]:
        """The learner's class (imported here if :attr:`cls` names it)."""
        if isinstance(self.cls, str):
            module, _, name = self.cls.partition(":")
            found: type[Learner] = vars(importlib.import_module(module))[name]
            return found
        return self.cls


class _LearnerClasses(dict[str, Any]):
    """The learner classes by name: a spec's class, imported when it is looked up."""

    def __getitem__(self, name: str) -> type[Learner]:
        return (
            LEARNER_SPECS[name].learner_class()
            if name in LEARNER_SPECS
            else super().__getitem__(name)
        )

    def get(self, name: str, default: Any = None) -> Any:
        return self[name] if name in self else default

    def values(self) -> Any:
        return [self[name] for name in self]

    def items(self) -> Any:
        return [(name, self[name]) for name in self]


_L = "mpcmobo.learners."
LEARNER_SPECS: dict[str, LearnerSpec] = {
    spec.name: spec
    for spec in (
        LearnerSpec("mpc-rl", _L + "mpc_rl:MPCRL", "MPC-RL", "tab:green", 1, True, MPCRLOptions),
        LearnerSpec("bo", _L + "gp:BOLearner", "BO", "grey", 3, True, BOOptions),
        LearnerSpec(
            "mobo", _L + "mobo:MOBOLearner", "MPC-RL-MOBO", "tab:red", 4, True, MOBOOptions
        ),
        LearnerSpec(
            "hybrid", _L + "mobo:HybridLearner", "hybrid", "tab:purple", 4, False, HybridOptions
        ),
        LearnerSpec(
            "identify",
            _L + "identified:IdentifyLearner",
            "identify",
            "tab:blue",
            1,
            False,
            IdentifyOptions,
        ),
    )
}
"""The learners by name, one entry each: what the settings, the CLI and the figures read."""
LEARNERS: dict[str, type[Learner]] = _LearnerClasses(dict.fromkeys(LEARNER_SPECS))
"""The learner classes by name (from :data:`LEARNER_SPECS`, imported when looked up)."""


def register_learner(spec: LearnerSpec) -> None:
    """Add a learner to this process's registry (e.g. a benchmark's peer learner). The
    settings, the job scheduler and the figures read it from there; spawned worker processes
    do not see it, so a study with such a learner runs with ``workers = 1``."""
    if spec.name in LEARNER_SPECS and LEARNER_SPECS[spec.name] != spec:
        raise ValueError(f"a different learner '{spec.name}' is already registered")
    LEARNER_SPECS[spec.name] = spec
    LEARNERS[spec.name] = spec.learner_class()


class LearnerOptionError(ValueError, TypeError):
    """An unknown or invalid learner option; the message names it and lists the learner's
    options."""


def _spec(name: str) -> LearnerSpec:
    if name not in LEARNER_SPECS:
        raise ValueError(f"unknown learner '{name}'; available: {', '.join(sorted(LEARNERS))}")
    return LEARNER_SPECS[name]


def learner_options(name: str) -> dict[str, Any]:
    """The options of the learner ``name`` and their defaults (tables as dicts)."""
    cls = _spec(name).options
    return {} if cls is None else cls().model_dump()


def option_fields(name: str) -> dict[str, Any]:
    """The options of ``name`` as pydantic fields (name -> FieldInfo), in their order: what
    the registry counts as the learner's user options."""
    cls = _spec(name).options
    return {} if cls is None else dict(cls.model_fields)


def describe_options(name: str) -> str:
    """``n_init = 5, refit_every = 10, ...``: the options of ``name`` with their defaults."""
    return ", ".join(f"{k} = {v!r}" for k, v in learner_options(name).items()) or "none"


# the names of the policy variants (``rule``): pydantic puts the chosen one into an error's path
_RULES = {"evidence", "incumbent", "adam", "gd", "verified", "iterate"}


def _problem(err: ValidationError, prefix: str) -> str:
    """The validation errors as ``prefix.key.path: message (got value)``, one per line.
    pydantic's own parts of a path (a policy variant's name, ``function-after[...]``,
    ``literal[False]``) are left out, and so is the error of the ``false`` alternative of a
    table when the table itself has errors."""
    errors = err.errors()
    tables = {e["loc"][0] for e in errors if e["type"] != "literal_error" and len(e["loc"]) > 1}
    out = []
    for e in errors:
        if e["type"] == "literal_error" and e["loc"] and e["loc"][0] in tables:
            continue  # "Input should be False" next to the table's own errors
        parts = [str(p) for p in e["loc"]]
        loc = ".".join(p for i, p in enumerate(parts) if not ((i and p in _RULES) or "[" in p))
        msg = "unknown option" if e["type"] == "extra_forbidden" else e["msg"]
        if msg.startswith("Value error, "):
            msg = msg[len("Value error, ") :]
        got = "" if e["type"] in ("extra_forbidden", "missing") else f" (got {e['input']!r})"
        out.append(f"{prefix}{loc}: {msg}{got}" if loc else f"{prefix.rstrip('.')}: {msg}")
    return "\n".join(out)


def validate_options(
    name: str, options: dict[str, Any] | BaseModel | None, prefix: str = ""
) -> BaseModel | None:
    """The options object of the learner ``name`` from a settings table; a problem is a
    :class:`LearnerOptionError` that names the option (after ``prefix``, e.g.
    ``"learner_options.bo."``) and lists the learner's options."""
    cls = _spec(name).options
    if cls is None:
        if options:
            raise LearnerOptionError(f"the learner '{name}' takes no options, got {options!r}")
        return None
    if isinstance(options, cls):
        return options
    try:
        return cls.model_validate(options or {})
    except ValidationError as err:
        listing = f"the options of '{name}' (with their defaults): {describe_options(name)}"
        raise LearnerOptionError(f"{_problem(err, prefix)}\n{listing}") from None


def switch_deploy(options: BaseModel | None) -> EvidenceDeploy:
    """The deployment options of identify-first's model switch: the learner's own evidence
    rule (its confidence and ``min_runs``; MPC-RL's verification: its confidence and
    ``runs``), else the default evidence rule (a learner on the paper's rules, or without
    options)."""
    deploy = options.deploy if isinstance(options, (BOOptions, MPCRLOptions)) else None
    if isinstance(deploy, EvidenceDeploy):
        return deploy
    if isinstance(deploy, VerifiedDeploy):
        return EvidenceDeploy(confidence=deploy.confidence, min_runs=deploy.runs)
    return EvidenceDeploy()


def _build(
    spec: LearnerSpec,
    opts: BaseModel | None,
    space: SearchSpace,
    theta0: np.ndarray,
    seed: int,
    starts: Starts | None,
    **extra: Any,
) -> Learner:
    """The learner of ``spec`` with the validated options ``opts``."""
    if spec.options is None:
        return spec.learner_class()(space, theta0, seed, starts=starts, **extra)
    cls: Any = spec.learner_class()  # a learner with options takes them after the seed
    return cls(space, theta0, seed, opts, starts=starts, **extra)


def make_learner(
    name: str,
    space: SearchSpace,
    theta0: np.ndarray,
    seed: int = 0,
    *,
    starts: Starts | None = None,
    model_fit: ModelFit | None = None,
    **options: Any,
) -> Learner:
    """Build the learner ``name`` ("mpc-rl", "bo", "mobo", "hybrid", "identify", or one
    registered) with its options (the keys of its settings table) for the study's start design
    ``starts`` (default: random). ``model_fit`` (:class:`~mpcmobo.identify.ModelFit`): the
    model to identify first; ``identify`` needs it, and any other learner given one is built
    as :class:`~mpcmobo.learners.identified.IdentifyFirst`, the model switch with the
    learner's deployment options (:func:`switch_deploy`), then the learner itself from the
    deployed theta. A bad option is a :class:`LearnerOptionError` (a ``ValueError``)."""
    from mpcmobo.learners.identified import IdentifyFirst

    spec = _spec(name)
    opts = validate_options(name, options)
    if name == "identify" or model_fit is None:
        extra = {} if model_fit is None else {"model_fit": model_fit}
        return _build(spec, opts, space, theta0, seed, starts, **extra)

    def inner(theta: np.ndarray) -> Learner:
        return _build(spec, opts, space, theta, seed, starts)

    return IdentifyFirst(
        inner,
        space,
        theta0,
        seed,
        name=name,
        starts=starts,
        model_fit=model_fit,
        deploy=switch_deploy(opts),
    )
