"""The settings of a study: one validated model, loaded from TOML, saved with every default.

A study is described by a :class:`Settings` object. ``load_settings(path, **overrides)`` reads a
TOML file (optional), applies overrides (``episodes=5``, ``mpc={"horizon": 8}`` or
``mpc__horizon=8``) and validates the result. Every problem is reported as a
:class:`SettingsError` whose message names the key as a dotted path (``mpc.horizon``) and what is
allowed there. Unknown keys are errors at every level.

``settings.resolved()`` fills the defaults that depend on the system (horizon, discount, episode
length, exploration noise, search-space options) so that ``DIR/config.toml`` of a run holds every
value that was used.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
)

from mpcmobo.learners.registry import LEARNER_SPECS, LearnerOptionError, validate_options
from mpcmobo.systems import (
    System,
    SystemDefinitionError,
    SystemSpecError,
    available_systems,
    get_system,
    make_plant,
)
from mpcmobo.systems.registry import is_factory_path, normalise_spec

# the learners the settings accept by name; those the paper's study runs; the default study's:
# the paper's and the identification baseline
KNOWN_LEARNERS = tuple(LEARNER_SPECS)
PAPER_LEARNERS = tuple(name for name, spec in LEARNER_SPECS.items() if spec.in_paper)
DEFAULT_LEARNERS = (*PAPER_LEARNERS, "identify")


class SettingsError(ValueError):
    """Invalid settings: the message names the key (dotted path) and what is allowed."""


class _Section(BaseModel):
    model_config = ConfigDict(
        extra="forbid",
        strict=True,
        allow_inf_nan=False,
        validate_assignment=True,
        use_attribute_docstrings=True,
    )


class SystemSettings(_Section):
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
    ``e^(+-model_log_range)``; unset: the system's. The same bounds hold for identification: a
    fit that ends on one is reported (``mpcmobo run`` warns, ``identified_at_bound`` in
    summary.json), as the plant's value may lie beyond it. Wider bounds cost nothing in the
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


class MPCSettings(_Section):
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
    only at IPOPT's solution (to its tolerance); else IPOPT solves. 0: IPOPT always (a step about
    twice as slow)."""
    codegen: bool = False
    """Generated C code of the MPC's functions, compiled once per machine and problem and cached
    (``$MPCMOBO_CACHE_DIR``, else ``~/.cache/mpcmobo``): the same numbers, faster steps; needs a
    C compiler; the first build takes tens of seconds."""

    def options(self) -> dict[str, Any]:
        """The options given to ``ParametricMPC`` (the unset ones left to the system)."""
        d = self.model_dump()
        return {k: v for k, v in d.items() if v is not None}


class ExplorationSettings(_Section):
    """Gaussian input noise of the learning episodes."""

    std: list[float] | None = None
    """Standard deviation of the noise added to each input; unset: 2% of each input's range."""
    decay: float = Field(1.0, gt=0, le=1)
    """The standard deviation is multiplied by this factor after every episode (1: constant)."""

    @field_validator("std")
    @classmethod
    def _nonnegative(cls, v: list[float] | None) -> list[float] | None:
        if v is not None and (len(v) == 0 or any(s < 0 for s in v)):
            raise ValueError("must be a non-empty list of numbers >= 0 (one per input)")
        return v


class CriticSettings(_Section):
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


class EvaluationSettings(_Section):
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


class RecordsSettings(_Section):
    """What is stored besides the per-episode rows."""

    trajectory_every: int = Field(20, ge=1)
    """Store every this many episodes the learning episode's states and inputs."""


class Settings(_Section):
    """Everything a study needs; a settings file holds any subset of it."""

    system: SystemSettings = Field(default_factory=SystemSettings)
    """The system, its plant and the MPC's parameterization."""
    mpc: MPCSettings = Field(default_factory=MPCSettings)
    """The parametric MPC."""
    exploration: ExplorationSettings = Field(default_factory=ExplorationSettings)
    """The exploration noise of learning episodes."""
    episodes: int = Field(600, ge=1, le=1_000_000)
    """Episodes per job (learner and seed)."""
    steps: int | None = Field(None, ge=1, le=1_000_000)
    """Time steps per episode; unset: the system's (60 on the CSTR)."""
    start_mode: Literal["random", "cycle"] = "cycle"
    """``"cycle"``: episode k starts from the (k mod ``n_cycle_starts``)-th of a fixed seeded set
    of initial states, so that thetas are compared from common starts; ``"random"``: a fresh
    initial state per episode (the paper's)."""
    n_cycle_starts: int = Field(6, ge=1, le=100_000)
    """Starts of the cycle (``start_mode = "cycle"``)."""
    critic: CriticSettings = Field(default_factory=CriticSettings)
    """The compatible critic."""
    beta: float = Field(1.0, gt=0, allow_inf_nan=False)
    """The weight beta > 0 of f4 (the Lyapunov decrease)."""
    learners: list[str] = Field(default_factory=lambda: list(DEFAULT_LEARNERS), min_length=1)
    """The learners of the study (``mpc-rl``, ``bo``, ``mobo``, ``hybrid``, ``identify``): by
    default the paper's three and ``identify``, the identification baseline (left out on a
    system that declares no model parameter to identify)."""
    learner_options: dict[str, dict[str, Any]] = Field(default_factory=dict)
    """A table of options per learner (below)."""
    evaluation: EvaluationSettings = Field(default_factory=EvaluationSettings)
    """The evaluation protocol."""
    records: RecordsSettings = Field(default_factory=RecordsSettings)
    """What is stored besides the per-episode rows."""
    seeds: list[int] = Field(default_factory=lambda: [0], min_length=1)
    """The seeds: one job per learner and seed."""
    workers: int = Field(2, ge=1, le=1024)
    """Jobs run in parallel (processes, or Ray tasks)."""
    backend: Literal["process", "ray"] = "process"
    """Where jobs run: local processes, or a Ray cluster (``pip install -e ".[ray]"``)."""

    @field_validator("learners")
    @classmethod
    def _known_learners(cls, v: list[str]) -> list[str]:
        for name in v:
            if name not in LEARNER_SPECS:  # read live: register_learner may add to it
                raise ValueError(f"unknown learner '{name}'; allowed: {', '.join(LEARNER_SPECS)}")
        if len(set(v)) != len(v):
            raise ValueError("each learner may appear only once")
        return v

    @field_validator("learner_options")
    @classmethod
    def _options_tables(cls, v: dict[str, dict[str, Any]]) -> dict[str, dict[str, Any]]:
        for name, table in v.items():
            if name not in LEARNER_SPECS:
                raise ValueError(
                    f"learner_options.{name}: options for an unknown learner; allowed: "
                    f"{', '.join(LEARNER_SPECS)}"
                )
            if not isinstance(table, dict):
                raise ValueError(f"'{name}' must be a table of options")
            try:
                validate_options(name, table, prefix=f"learner_options.{name}.")
            except LearnerOptionError as err:
                raise ValueError(str(err)) from None
        return v

    @field_validator("seeds")
    @classmethod
    def _seeds(cls, v: list[int]) -> list[int]:
        if any(s < 0 or s >= 2**63 for s in v):
            raise ValueError("seeds must be integers in [0, 2**63)")
        if len(set(v)) != len(v):
            raise ValueError("each seed may appear only once")
        return v

    @model_validator(mode="after")
    def _fits_system(self) -> Settings:
        identify = "learners" in self.model_fields_set and "identify" in self.learners
        if self.exploration.std is None and not self.system.learn_model and not identify:
            return self  # nothing system-specific to check; avoid building the system
        try:
            system = build_system(self)
        except SettingsError as err:
            raise ValueError(str(err)) from None
        except Exception as err:  # noqa: BLE001 - reported as a settings problem
            raise ValueError(f"system settings: {err}") from None
        std = self.exploration.std
        if std is not None and len(std) != system.nu:
            raise ValueError(
                f"exploration.std has {len(std)} entries; the system '{system.name}' has "
                f"{system.nu} inputs {list(system.input_names)}"
            )
        if identify and not system.identifiable:
            raise ValueError(
                f"learners: the system '{system.name}' declares no model parameter to identify "
                "(System.param_names): remove 'identify'"
            )
        return self

    # ------------------------------------------------------------------ derived
    def resolved(self) -> Settings:
        """A copy with the system-dependent defaults filled in (what ``config.toml`` stores)."""
        system = build_system(self)
        spec = system.mpc_spec
        d = self.model_dump()
        if self.system.factory is not None:
            d["system"]["name"] = system.name
        d["system"]["weight_log_range"] = float(spec.weight_log_range)
        d["system"]["model_log_range"] = float(spec.model_log_range)
        d["mpc"]["horizon"] = int(spec.horizon if self.mpc.horizon is None else self.mpc.horizon)
        d["mpc"]["gamma"] = float(spec.gamma if self.mpc.gamma is None else self.mpc.gamma)
        d["steps"] = int(system.episode_steps if self.steps is None else self.steps)
        if "learners" not in self.model_fields_set and not system.identifiable:
            d["learners"] = [n for n in d["learners"] if n != "identify"]  # nothing to identify
        if self.exploration.std is None:
            span = system.u_ub - system.u_lb
            d["exploration"]["std"] = [
                float(0.02 * s) if math.isfinite(s) else 0.1 for s in span.tolist()
            ]
        if self.evaluation.steps is None:
            d["evaluation"]["steps"] = d["steps"]
        d["learner_options"] = {  # every learner option in force, defaults filled in
            name: _options_dump(name, self.learner_options.get(name, {}))
            for name in dict.fromkeys([*self.learners, *self.learner_options])
        }
        return validate_settings(d)

    def to_dict(self) -> dict[str, Any]:
        """Plain dict without ``None`` values (TOML has no null)."""
        return _drop_none(self.model_dump())


def _options_dump(name: str, table: dict[str, Any]) -> dict[str, Any]:
    """The learner's options in force as a plain table (every default filled in)."""
    options = validate_options(name, table)
    return {} if options is None else options.model_dump()


def _drop_none(d: Any) -> Any:
    if isinstance(d, dict):
        return {k: _drop_none(v) for k, v in d.items() if v is not None}
    if isinstance(d, list):
        return [_drop_none(v) for v in d]
    return d


def build_system(settings: Settings, learner: str | None = None) -> System:
    """The system of the settings, with its MPC-spec overrides applied; for ``learner``'s job
    with the parameters it identifies in theta (:func:`identified_parameters`). A system that
    cannot be found, imported or built is a :class:`SettingsError` (one line, naming the key)."""
    key = "system.factory" if settings.system.factory is not None else "system.name"
    try:
        system = get_system(settings.system.spec, **settings.system.spec_overrides())
        _known_parameters(settings.system.learn_model, system, "system.learn_model")
        names = identified_parameters(settings, system, learner)
        if not names:
            return system
        return get_system(
            settings.system.spec, **settings.system.spec_overrides(), identify=tuple(names)
        )
    except (SystemSpecError, SystemDefinitionError) as err:
        raise SettingsError(f"{key}: {err}") from None
    except ValueError as err:  # an MPC setting the system refuses (or a key named above)
        raise err if isinstance(err, SettingsError) else SettingsError(f"system: {err}") from None


def _known_parameters(names: Sequence[str], system: System, key: str) -> None:
    """A :class:`SettingsError` at ``key`` if ``names`` has a parameter the system lacks."""
    known = list(system.param_names)
    if unknown := [n for n in names if n not in known]:
        raise SettingsError(f"{key}: unknown model parameter(s) {unknown}; the system has {known}")


def identified_parameters(
    settings: Settings, system: System, learner: str | None
) -> tuple[str, ...]:
    """The model parameters ``learner``'s job identifies: ``[system] identify`` (``true``: the
    system's identifiable ones, ``param_names``), and those for the ``identify`` learner; none
    without a learner (the study's reference)."""
    ident = settings.system.identify
    if learner is None:
        return ()
    if isinstance(ident, list) and ident:
        _known_parameters(ident, system, "system.identify")
        return tuple(ident)
    if ident is True or learner == "identify":
        return tuple(system.identifiable or ())
    return ()


def needs_plant(settings: Settings) -> bool:
    """Whether a study builds its plant (:func:`build_plant`): a plant of the settings, or the
    system's own with noise; else the closed loop runs the system's equations itself."""
    return settings.system.plant is not None or settings.system.noisy


def build_plant(settings: Settings, system: System) -> Any:
    """The plant of the settings (``system.plant``, default the system's equations with the
    settings' noise), checked against the system's sizes; a problem is a
    :class:`SettingsError`."""
    try:
        return make_plant(
            settings.system.plant,
            system,
            process_noise=settings.system.process_noise,
            measurement_noise=settings.system.measurement_noise,
        )
    except (SystemSpecError, SystemDefinitionError) as err:
        key = "system.plant" if settings.system.plant is not None else "system"
        raise SettingsError(f"{key}: {err}") from None


# ---------------------------------------------------------------------- errors and loading
def _field_names(model: type[BaseModel], loc: tuple) -> list[str] | None:
    """The allowed keys of the section at ``loc`` (for unknown-key messages)."""
    cls: Any = model
    for part in loc:
        if not (isinstance(cls, type) and issubclass(cls, BaseModel)):
            return None
        field = cls.model_fields.get(str(part))
        if field is None:
            return None
        cls = field.annotation
    if isinstance(cls, type) and issubclass(cls, BaseModel):
        return list(cls.model_fields)
    return None


def _format_error(err: Mapping[str, Any]) -> str:
    loc = tuple(err.get("loc", ()))
    key = ".".join(str(p) for p in loc) or "(top level)"
    typ = err.get("type", "")
    if typ == "extra_forbidden":
        allowed = _field_names(Settings, loc[:-1])
        hint = f"; allowed keys here: {', '.join(allowed)}" if allowed else ""
        return f"{key}: unknown key{hint}"
    msg = str(err.get("msg", "invalid value"))
    if msg.startswith("Value error, "):
        msg = msg[len("Value error, ") :]
    value = err.get("input")
    shown = repr(value)
    if len(shown) > 60:
        shown = shown[:57] + "..."
    if not loc:  # a check across sections: its message names the keys itself
        return msg
    if loc[0] == "learner_options" and msg.startswith("learner_options"):
        return msg.replace("\n", "\n  ")  # the learners' options name their keys themselves
    if typ in ("missing",):
        return f"{key}: {msg}"
    return f"{key}: {msg} (got {shown})"


def validate_settings(data: Any) -> Settings:
    """Validate a TOML-like dict; any problem is a :class:`SettingsError`."""
    if not isinstance(data, dict):
        raise SettingsError(f"settings must be a table of keys, got {type(data).__name__}")
    try:
        return Settings.model_validate(data)
    except ValidationError as err:
        lines = [_format_error(e) for e in err.errors()]
        raise SettingsError("invalid settings:\n  " + "\n  ".join(lines)) from None
    except SettingsError:
        raise
    except (ValueError, TypeError, KeyError, OverflowError, RecursionError) as err:
        raise SettingsError(f"invalid settings: {err}") from None


def _merge(base: dict, extra: dict) -> dict:
    out = dict(base)
    for k, v in extra.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def _nest(overrides: dict[str, Any]) -> dict[str, Any]:
    """``{"mpc__horizon": 8, "episodes": 5}`` -> ``{"mpc": {"horizon": 8}, "episodes": 5}``."""
    out: dict[str, Any] = {}
    for key, value in overrides.items():
        if value is None:
            continue
        parts = key.replace(".", "__").split("__")
        node = out
        for p in parts[:-1]:
            nxt = node.setdefault(p, {})
            if not isinstance(nxt, dict):
                raise SettingsError(f"{key}: cannot set a key inside a non-table value")
            node = nxt
        last = parts[-1]
        if isinstance(value, dict) and isinstance(node.get(last), dict):
            node[last] = _merge(node[last], value)
        else:
            node[last] = value
    return out


def read_toml(path: str | Path) -> dict[str, Any]:
    """The TOML file at ``path`` as a dictionary; a missing or malformed file is a
    ``SettingsError``."""
    path = Path(path)
    try:
        with path.open("rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise SettingsError(f"settings file not found: {path}") from None
    except tomllib.TOMLDecodeError as err:
        raise SettingsError(f"{path}: not valid TOML: {err}") from None
    except (OSError, UnicodeDecodeError) as err:
        raise SettingsError(f"{path}: cannot read: {err}") from None


def load_settings(path: str | Path | None = None, **overrides: Any) -> Settings:
    """Settings from an optional TOML file plus overrides (``None`` overrides are ignored).

    Overrides are top-level keys (``episodes=5``), section tables (``mpc={"horizon": 8}``, merged
    into the file's table) or double-underscore paths (``mpc__horizon=8``).
    """
    return settings_from(read_toml(path) if path is not None else {}, **overrides)


def settings_from(data: dict[str, Any], **overrides: Any) -> Settings:
    """Settings from a TOML-like table (a file already read) plus overrides, as
    :func:`load_settings` merges them."""
    return validate_settings(_merge(data, _nest(overrides)))


def settings_to_toml(settings: Settings) -> str:
    """The settings as TOML text (what ``config.toml`` holds)."""
    import tomli_w

    return tomli_w.dumps(settings.to_dict())
