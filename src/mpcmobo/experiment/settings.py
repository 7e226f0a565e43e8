"""The settings of a study: one validated model, loaded from TOML, saved with every default.

A study is described by a :class:`Settings` object. ``load_settings(path, **overrides)`` reads a
TOML file (optional), applies overrides (``episodes=5``, ``mpc={"horizon": 8}`` or
``mpc__horizon=8``) and validates the result. Every problem is reported as a
:class:`SettingsError` whose message names the key as a dotted path (``mpc.horizon``) and what is
allowed there. Unknown keys are errors at every level.

``settings.resolved()`` fills the defaults that depend on the system (horizon, discount, episode
length, exploration noise, search-space options) so that ``DIR/config.toml`` of a run holds every
value that was used.

The tables are the models of :mod:`~mpcmobo.experiment.sections`; the system and the plant that
settings describe are built by :mod:`~mpcmobo.experiment.build`.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any, Literal

from pydantic import BaseModel, Field, ValidationError, field_validator, model_validator

from mpcmobo.experiment.build import build_system
from mpcmobo.experiment.sections import (
    CriticSettings,
    EvaluationSettings,
    ExplorationSettings,
    MPCSettings,
    RecordsSettings,
    Section,
    SettingsError,
    SystemSettings,
)
from mpcmobo.learners.registry import LEARNER_SPECS, LearnerOptionError, validate_options

if TYPE_CHECKING:
    from mpcmobo.systems import System

# the learners the settings accept by name; those the paper's study runs; the default study's:
# the paper's and the identification baseline
KNOWN_LEARNERS = tuple(LEARNER_SPECS)
PAPER_LEARNERS = tuple(name for name, spec in LEARNER_SPECS.items() if spec.in_paper)
DEFAULT_LEARNERS = (*PAPER_LEARNERS, "identify")


class Settings(Section):
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
    cycle_starts: list[list[float]] | None = Field(None, min_length=1, max_length=100_000)
    """The cycle's initial states themselves (``start_mode = "cycle"``), each a list of the
    system's state values in the order of its state names, within its state bounds: the
    recipes a batch plant is started from. Their number is ``n_cycle_starts``. Unset:
    ``n_cycle_starts`` states drawn from the system's initial-state distribution with each
    job's seed."""
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

    @model_validator(mode="before")
    @classmethod
    def _cycle_count(cls, data: Any) -> Any:
        """``n_cycle_starts`` as the number of ``cycle_starts``, where only those are given."""
        if not isinstance(data, Mapping) or "n_cycle_starts" in data:
            return data
        starts = data.get("cycle_starts")
        if isinstance(starts, list) and starts:
            return {**data, "n_cycle_starts": len(starts)}
        return data

    @model_validator(mode="after")
    def _cycle_starts(self) -> Settings:
        starts = self.cycle_starts
        if starts is None:
            return self
        if self.start_mode != "cycle":
            raise ValueError(
                f"cycle_starts: the cycle's starts apply under start_mode = 'cycle' (here "
                f"'{self.start_mode}', where every episode starts from a fresh state)"
            )
        if self.n_cycle_starts != len(starts):
            raise ValueError(
                f"n_cycle_starts is {self.n_cycle_starts} but cycle_starts holds {len(starts)} "
                "states: give one of them, or the same number"
            )
        return self

    @model_validator(mode="after")
    def _fits_system(self) -> Settings:
        identify = "learners" in self.model_fields_set and "identify" in self.learners
        starts = self.cycle_starts
        checks = self.exploration.std is not None or self.system.learn_model or identify
        if not checks and starts is None:
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
        if starts is not None:
            _check_cycle_starts(starts, system)
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


def _check_cycle_starts(starts: list[list[float]], system: System) -> None:
    """Each of ``cycle_starts`` a finite state of ``system`` within its state bounds; else a
    ``ValueError`` naming the start and the state."""
    names = list(system.state_names)
    for k, x0 in enumerate(starts):
        if len(x0) != system.nx:
            values = f"{len(x0)} value{'' if len(x0) == 1 else 's'}"
            raise ValueError(
                f"cycle_starts[{k}] has {values}; the system '{system.name}' has {system.nx} "
                f"states {names}"
            )
        for j, v in enumerate(x0):
            lo, hi = float(system.x_lb[j]), float(system.x_ub[j])
            if not (math.isfinite(v) and lo <= v <= hi):
                raise ValueError(
                    f"cycle_starts[{k}]: {names[j]} = {v} is outside the system's state "
                    f"bounds [{lo:g}, {hi:g}]"
                )


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
    :func:`load_settings` merges them; the file's values that the overrides replace are
    checked too (:func:`_check_overridden`)."""
    nested = _plain(_nest(overrides))
    _check_overridden(data, nested)
    return validate_settings(_merge(data, nested))


def _plain(value: Any) -> Any:
    """``value`` with NumPy arrays and scalars (anything with ``tolist``) as the lists and
    numbers a settings file holds, in tables and lists too: ``Tuner(...,
    cycle_starts=np.array(recipes))`` as ``cycle_starts = [[...], ...]``."""
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_plain(v) for v in value]
    tolist = getattr(value, "tolist", None)
    return tolist() if callable(tolist) else value


def _overridden(data: dict[str, Any], nested: dict[str, Any], prefix: tuple = ()) -> list[tuple]:
    """The key paths of ``data``'s values that the (nested) overrides replace."""
    out: list[tuple] = []
    for key, value in nested.items():
        if key not in data:
            continue
        if isinstance(value, dict) and isinstance(data[key], dict):
            out += _overridden(data[key], value, (*prefix, key))
        else:
            out.append((*prefix, key))
    return out


def _check_overridden(data: dict[str, Any], nested: dict[str, Any]) -> None:
    """A wrong value in a settings file is refused even where the command line (or a caller's
    keyword) sets the same key: the file's own values, with the overrides only where the file
    is silent, are validated, and an error at a key the overrides replace is a
    :class:`SettingsError` (other errors are the merged settings' to report)."""
    paths = _overridden(data, nested)
    if not paths:
        return
    try:
        Settings.model_validate(_merge(nested, data))
    except ValidationError as err:
        found = [
            e for e in err.errors() if any(tuple(e.get("loc", ()))[: len(p)] == p for p in paths)
        ]
        if found:
            lines = [_format_error(e) for e in found]
            raise SettingsError(
                "invalid settings in the file (where the command line sets the same keys, "
                "the file's values must be valid too):\n  " + "\n  ".join(lines)
            ) from None
    except (SettingsError, ValueError, TypeError, KeyError):
        return  # a check across sections: the merged settings' validation reports it


def settings_to_toml(settings: Settings) -> str:
    """The settings as TOML text (what ``config.toml`` holds)."""
    import tomli_w

    return tomli_w.dumps(settings.to_dict())
