"""Learners by name: one :class:`LearnerSpec` per learner carries everything the package knows
about it (class, label and colour in the figures, scheduling cost, whether the paper runs it).
Adding a learner is one entry in ``LEARNER_SPECS``."""

from __future__ import annotations

import inspect
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from mpcmobo.learners.base import Learner
from mpcmobo.learners.bo import BOLearner, HybridLearner, MOBOLearner
from mpcmobo.learners.mpc_rl import MPCRL
from mpcmobo.systems.space import SearchSpace


@dataclass(frozen=True)
class LearnerSpec:
    """One learner: its settings name, class, figure label and colour, its relative cost per
    episode (used only to start the slowest jobs first; measured in docs/benchmarks.md: the
    EHVI learners spend the most per episode, MPC-RL the least), and whether the paper's
    study runs it (the default ``learners`` of the settings)."""

    name: str
    cls: type[Learner]
    label: str
    color: str
    job_cost: int
    in_paper: bool


LEARNER_SPECS: dict[str, LearnerSpec] = {
    spec.name: spec
    for spec in (
        LearnerSpec("mpc-rl", MPCRL, "MPC-RL", "tab:green", job_cost=1, in_paper=True),
        LearnerSpec("bo", BOLearner, "BO", "grey", job_cost=3, in_paper=True),
        LearnerSpec("mobo", MOBOLearner, "MPC-RL-MOBO", "tab:red", job_cost=4, in_paper=True),
        LearnerSpec("hybrid", HybridLearner, "hybrid", "tab:purple", job_cost=4, in_paper=False),
    )
}
"""The learners by name, one entry each: what the settings, the CLI and the figures read."""
LEARNERS: dict[str, type[Learner]] = {name: spec.cls for name, spec in LEARNER_SPECS.items()}
"""The learner classes by name (from :data:`LEARNER_SPECS`)."""


def register_learner(spec: LearnerSpec) -> None:
    """Add a learner to this process's registry (e.g. a benchmark's peer learner). The
    settings, the job scheduler and the figures read it from there; spawned worker processes
    do not see it, so a study with such a learner runs with ``workers = 1``."""
    if spec.name in LEARNER_SPECS and LEARNER_SPECS[spec.name] != spec:
        raise ValueError(f"a different learner '{spec.name}' is already registered")
    LEARNER_SPECS[spec.name] = spec
    LEARNERS[spec.name] = spec.cls


# the constructor arguments of every learner that are not options
_NOT_OPTIONS = ("self", "space", "theta0", "seed")


class LearnerOptionError(ValueError, TypeError):
    """An unknown or invalid learner option; the message lists the learner's options. A
    ``ValueError`` and, as an unknown option always was, a ``TypeError``."""


def learner_options(name: str) -> dict[str, Any]:
    """The options of the learner ``name`` and their defaults, read from the keyword arguments
    of its class's constructor and those of its base classes (a subclass's default wins), so
    that an option added to a learner is known here without further change."""
    if name not in LEARNERS:
        raise ValueError(f"unknown learner '{name}'; available: {', '.join(sorted(LEARNERS))}")
    options: dict[str, Any] = {}
    for cls in LEARNERS[name].__mro__:
        init = cls.__dict__.get("__init__")
        if init is None:
            continue
        for p in inspect.signature(init).parameters.values():
            if p.name in _NOT_OPTIONS or p.kind in (p.VAR_KEYWORD, p.VAR_POSITIONAL):
                continue
            if p.default is not p.empty:
                options.setdefault(p.name, p.default)
    return options


def describe_options(name: str) -> str:
    """``n_init = 5, refit_every = 10, ...``: the options of ``name`` with their defaults."""
    return ", ".join(f"{k} = {v!r}" for k, v in learner_options(name).items())


def _type_problem(key: str, value: Any, default: Any) -> str | None:
    """What is wrong with the type of ``value`` given the option's default (None: nothing
    that can be told from the default)."""
    if isinstance(default, bool):
        ok = isinstance(value, bool)
        want = "true or false"
    elif isinstance(default, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
        want = "an integer"
    elif isinstance(default, float):
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        want = "a number"
        if ok and math.isnan(value):
            return f"{key} = {value!r}: must be a number, not NaN"
    elif isinstance(default, str):
        ok, want = isinstance(value, str), "a string"
    else:
        return None
    return None if ok else f"{key} = {value!r}: must be {want}"


def make_learner(
    name: str, space: SearchSpace, theta0: np.ndarray, seed: int = 0, **options: Any
) -> Learner:
    """Build the learner ``name`` ("mpc-rl", "bo", "mobo", "hybrid") with its options.

    An unknown option, one of the wrong type, or one its learner rejects raises a
    :class:`LearnerOptionError` (a ``ValueError``) listing the learner's options and defaults
    (:func:`learner_options`). Options the learner's constructor takes through ``**kwargs``
    (e.g. removed options at their old "off" value) are left to it.
    """
    allowed = learner_options(name)
    listing = f"the options of '{name}' (with their defaults): {describe_options(name)}"
    problems = [
        p
        for key, value in options.items()
        if key in allowed and (p := _type_problem(key, value, allowed[key])) is not None
    ]
    if problems:
        raise LearnerOptionError(f"{'; '.join(problems)}; {listing}")
    unknown = [k for k in options if k not in allowed]
    try:
        return LEARNERS[name](space, theta0, seed, **options)
    except (TypeError, ValueError) as err:
        if unknown and isinstance(err, TypeError):
            what = "unexpected learner option" + ("s " if len(unknown) > 1 else " ")
            raise LearnerOptionError(
                f"{what}{', '.join(repr(k) for k in unknown)}; {listing}"
            ) from None
        raise LearnerOptionError(f"{err}; {listing}") from None
