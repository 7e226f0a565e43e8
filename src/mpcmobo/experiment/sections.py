"""The tables of a settings file, one pydantic model each, and the error bad settings raise.

Each section (``[system]``, ``[mpc]``, ``[exploration]``, ``[critic]``, ``[evaluation]``,
``[records]``) is a strict model: unknown keys, wrong types and values out of range are errors,
and each field's docstring is its documentation (``docs/configuration.md`` is generated from
them). :class:`~mpcmobo.experiment.settings.Settings` assembles them.
"""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator

from mpcmobo.systems import available_systems
from mpcmobo.systems.registry import is_factory_path, normalise_spec


class SettingsError(ValueError):
    """Invalid settings: the message names the key (dotted path) and what is allowed."""


class Section(BaseModel):
    """A table of the settings: strict types, no unknown keys, no inf or nan, checked on
    assignment too; each field's docstring is its description."""

    model_config = ConfigDict(
        extra="forbid",
        strict=True,
        allow_inf_nan=False,
        validate_assignment=True,
        use_attribute_docstrings=True,
    )


class SystemSettings(Section):
    """Which system (the MPC's model), which plant, and how the MPC is parameterised
    (overrides of ``System.mpc_spec``)."""

    # factory before name: the name is checked only without a factory (``_known_system``)
    factory: str | None = None
    """The system's factory, ``"module:function"`` or ``"path/file.py:function"`` (a function
    that returns a ``mpcmobo.systems.System``); unset: the system ``name``."""
    name: str = "cstr"
    """A registered system or plug-in (``mpcmobo systems``); with ``factory``: the name of the
    system it builds."""
    plant: str | None = None
    """The plant: a gymnasium id or the factory of a ``gymnasium.Env``; unset: the system's own
    equations with its true parameters."""
    learn_model: list[str] = Field(default_factory=list)
    """Model parameters made learnable (part of theta, searched around their nominal value)."""
    learn_backoff: bool = False
    """Constraint back-offs of the state bounds made learnable (part of theta)."""
    learn_theta_c: bool = False
    """Search the cost's constant ``theta_c`` too (it changes V but never the policy)."""
    full_weights: bool = False
    """Full positive-definite MPC weights (Cholesky factors in theta) instead of diagonal."""
    weight_log_range: float | None = Field(None, gt=0, le=20)
    """The cost weights are searched within theta0's times ``e^(+-weight_log_range)``; unset: the
    system's (4 on the CSTR)."""
    model_log_range: float | None = Field(None, gt=0, le=10)
    """Learnable model parameters are searched within their nominal value times
    ``e^(+-model_log_range)`` (a nominal value of 0 or below: within it plus or minus
    ``model_log_range |nominal| + 1``); unset: the system's. The same bounds hold for
    identification: a fit that ends on one is reported (``mpcmobo run`` warns,
    ``identified_at_bound`` in summary.json), as the plant's value may lie beyond it. Wider bounds cost nothing in the
    fit; for learnable model parameters they widen the search."""
    process_noise: list[float] | None = None
    """Standard deviation of Gaussian noise added to each state by every step of the system's
    own plant (seeded per episode from the study's seed); unset: none."""
    measurement_noise: list[float] | None = None
    """Standard deviation of Gaussian noise on each state the system's own plant reports to
    the MPC, the learners and the identification; unset: none."""
    identify: bool | list[str] = True
    """Identify the model first: after every episode the model parameters (``true``: all the
    system declares; a list: those) are fitted to the plant's transitions, and each learner
    tunes from the identified model once its evidence supports it (a few episodes of the
    study; the fit itself takes a fraction of a second). On the identified model theta is
    first tuned on the twin, the model's closed loop in simulation (once per job, about a
    minute on the CSTR), and every candidate is judged by the twin calibrated on the plant's
    episodes (64 simulated closed loops per theta judged). ``false``: the learners tune the
    nominal model (the paper's method), and each deployment rests on the plant's episodes
    alone: slower, and under random starts a GP learner's candidate needs twice ``min_runs``
    episodes, so that a run of cheap starts is less likely to pass for a better theta (on
    the CSTR in 50 episodes, mobo at 4.10 x J* in median against 0.78 with identification,
    ``docs/benchmarks.md``).
    The ``identify`` learner identifies these, or all parameters when this is ``false``. A
    system that declares no model parameter has nothing to identify and tunes as with
    ``false``."""

    @field_validator("learn_model", "identify")
    @classmethod
    def _once_each(cls, v: bool | list[str]) -> bool | list[str]:
        if isinstance(v, list) and len(set(v)) != len(v):
            raise ValueError("each model parameter may appear only once")
        return v

    @field_validator("factory", "plant")
    @classmethod
    def _factory_path(cls, v: str | None) -> str | None:
        if v is None:
            return v
        if not v:
            raise ValueError("must be a non-empty string")
        return normalise_spec(v)  # a file path made absolute; the import is checked at build

    @field_validator("name")
    @classmethod
    def _known_system(cls, v: str, info: ValidationInfo) -> str:
        if info.data.get("factory") is None and v not in available_systems():
            if is_factory_path(v):
                raise ValueError(f"'{v}' is a factory path; give it as system.factory")
            if v.endswith(".py"):
                raise ValueError(f"'{v}' names a file: add its function, '{v}:make_system'")
            raise ValueError(
                f"unknown system '{v}'; allowed: {', '.join(available_systems())}; or a "
                "system.factory ('module:function' or 'path/file.py:function')"
            )
        return v

    @field_validator("process_noise", "measurement_noise")
    @classmethod
    def _noise_levels(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and (len(v) == 0 or any(s < 0 for s in v)):
            raise ValueError("must be a list of numbers >= 0 (one per state)")
        return v

    @property
    def noisy(self) -> bool:
        """Whether the system's own plant adds noise."""
        levels = [*(self.process_noise or []), *(self.measurement_noise or [])]
        return any(s > 0 for s in levels)

    @property
    def spec(self) -> str:
        """What names the system for :func:`~mpcmobo.systems.get_system`."""
        return self.factory if self.factory is not None else self.name

    def spec_overrides(self) -> dict[str, Any]:
        """The overrides of the system's ``MPCSpec`` that these settings ask for."""
        out: dict[str, Any] = {"learn_model": tuple(self.learn_model)} if self.learn_model else {}
        out |= {
            k: True for k in ("learn_backoff", "learn_theta_c", "full_weights") if getattr(self, k)
        }
        for k in ("weight_log_range", "model_log_range"):
            if getattr(self, k) is not None:
                out[k] = getattr(self, k)
        return out


class MPCSettings(Section):
    """Horizon, discount and solver options of the parametric MPC."""

    horizon: int | None = Field(None, ge=1, le=500)
    """Prediction horizon N; unset: the system's (10 on the CSTR)."""
    gamma: float | None = Field(None, gt=0, le=1)
    """Discount of the MPC cost and of f1; unset: the system's (0.99 on the CSTR)."""
    tau: float = Field(1e-6, gt=0, lt=1)
    """Barrier parameter at which the MPC is solved and differentiated (scaled units): the
    sensitivities are those of the barrier problem, smooth across active-set changes."""
    tol: float = Field(1e-8, gt=0, lt=1)
    """IPOPT's tolerance (and the Newton steps')."""
    max_iter: int = Field(150, ge=1, le=100_000)
    """IPOPT's iteration limit per solve; a solve that reaches it uses the fallback input."""
    warm_start: bool = True
    """Start each solve from the previous solution shifted by one step."""
    newton_steps: int = Field(6, ge=0, le=100)
    """Warm solves first try this many Newton steps on the barrier KKT system and accept them
    only at IPOPT's solution (to its tolerance); else the interior-point continuation on the
    same system (from the re-centred warm start, then restarted from the shifted plan on the
    central path; from the cold guess without a warm start), accepted at a minimum; else IPOPT
    solves. 0: IPOPT always (no Newton steps, no continuation: a step several times slower)."""
    codegen: bool | Literal["auto"] = "auto"
    """Generated C code of the MPC's functions, compiled once per machine and problem and cached
    (``$MPCMOBO_CACHE_DIR``, else ``~/.cache/mpcmobo``): the same numbers, about 1.6 times
    faster learning episodes; the first build of a problem takes tens of seconds. ``"auto"``:
    where a C compiler (``$CC``, else ``cc``) is found, else CasADi's virtual machine; ``true``
    needs the compiler; ``false``: never."""

    def options(self) -> dict[str, Any]:
        """The options given to ``ParametricMPC`` (the unset ones left to the system)."""
        d = self.model_dump()
        return {k: v for k, v in d.items() if v is not None}


class ExplorationSettings(Section):
    """Gaussian input noise of the learning episodes."""

    std: list[float] | None = None
    """Standard deviation of the noise added to each input; unset: 2% of each input's range."""
    decay: float = Field(1.0, gt=0, le=1)
    """The standard deviation is multiplied by this factor after every episode (1: constant)."""
    budget: float = Field(0.5, ge=0, allow_inf_nan=True)
    """The price an exploring episode may have: how much more than the deployed controller a
    candidate may cost from the coming start, as predicted on the learner's model and bounded
    by the model's record of errors, as a fraction of the deployed controller's predicted cost
    (0.5: at most 1.5x). A candidate over it does not run (the deployed controller runs
    instead); where the model's error is within 5%, neither does one that cannot pay back its
    excess within the remaining episodes, and the learner learns from the candidate's episode
    simulated on the model. After 5 refused or unpaid candidates in a row (20 simulated),
    tuning stops exploring (docs/real-plant.md). ``inf``: every candidate runs and nothing is
    predicted. Costs two closed loops on the model per exploring episode, and a closed loop
    and a learner's update per simulated candidate."""

    @field_validator("budget")
    @classmethod
    def _not_nan(cls, v: float) -> float:
        if math.isnan(v):
            raise ValueError("must be a number >= 0, or inf (no budget)")
        return v

    @field_validator("std")
    @classmethod
    def _nonnegative(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and (len(v) == 0 or any(s < 0 for s in v)):
            raise ValueError("must be a non-empty list of numbers >= 0 (one per input)")
        return v


class CriticSettings(Section):
    """The compatible critic (LSTDV and LSTDQ) and the policy gradient."""

    ridge: float = Field(1e-6, ge=0)
    """Relative ridge of the least-squares solves (numerical safety only)."""
    method: Literal["lstd", "paper"] = "lstd"
    """``"lstd"``: LSTDV with the TD target of V^nu; ``"paper"``: the value critic as printed
    in eq. lstdv_update (nu regresses the TD error of V_theta on grad V_theta)."""
    q_target: Literal["V_theta", "V_nu"] | None = None
    """Value of x_{k+1} in the LSTDQ target; unset: ``V_nu`` with ``"lstd"``, ``V_theta`` with
    ``"paper"``."""
    min_valid_steps: int = Field(2, ge=1)
    """With fewer usable transitions the episode's critic fit fails (no gradient)."""
    weighting: Literal["uniform", "discounted"] = "uniform"
    """The mean of the per-step DPG terms: uniform (the paper's eq. DPG) or discounted by
    gamma^k."""


class EvaluationSettings(Section):
    """The evaluation protocol: J_eval, the mean stage cost of the deployed theta from
    ``n_starts`` fixed initial states without exploration."""

    n_starts: int = Field(10, ge=1, le=10_000)
    """Initial states of the evaluation (drawn with ``seed``; never shown to a learner)."""
    seed: int = Field(2025, ge=0)
    """Seed of the evaluation starts."""
    steps: int | None = Field(None, ge=1, le=1_000_000)
    """Steps per evaluation episode; unset: ``steps``."""
    eval_every: int = Field(10, ge=1)
    """The deployed theta is evaluated when it changes, at most every this many episodes, and
    at the first and last episode."""


class RecordsSettings(Section):
    """What is stored besides the per-episode rows."""

    trajectory_every: int = Field(20, ge=1)
    """Store every this many episodes the learning episode's states and inputs."""
