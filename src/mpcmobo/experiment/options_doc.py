"""The configuration reference, generated from the settings' and the learners' docstrings.

:func:`configuration_reference` is the page ``docs/configuration.md`` (a test keeps the
committed page equal to it); :func:`learner_option_lines` the learner options as
``mpcmobo run --help`` lists them. Every field of :class:`~mpcmobo.experiment.settings.Settings`
and of each learner's options class appears with its key, type, default and docstring; a table
of policy variants (``deploy``, ``optimizer``) lists each variant's fields.
"""

from __future__ import annotations

import types
import typing
from collections.abc import Iterator
from typing import Any

from pydantic import BaseModel
from pydantic.fields import FieldInfo

from mpcmobo.experiment.settings import Settings
from mpcmobo.learners.registry import LEARNER_SPECS

__all__ = ["configuration_reference", "learner_option_lines"]


def _models(annotation: Any) -> list[type[BaseModel]]:
    """The pydantic models in a field's annotation (a model, a union of them, Annotated)."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return [annotation]
    args = typing.get_args(annotation)
    if typing.get_origin(annotation) is typing.Annotated:
        return _models(args[0])
    return [m for a in args for m in _models(a)]


def _type_name(annotation: Any) -> str:
    """A short readable type: ``int``, ``float | None``, ``"cycle" | "random"``, ``table``."""
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:
        return _type_name(typing.get_args(annotation)[0])
    if origin is typing.Literal:
        return " | ".join(_literal(a) for a in typing.get_args(annotation))
    if origin in (typing.Union, types.UnionType):
        return " | ".join(_type_name(a) for a in typing.get_args(annotation))
    if origin in (list, tuple):
        args = typing.get_args(annotation)
        return f"list of {_type_name(args[0])}" if args else "list"
    if origin is dict:
        return "table"
    if annotation is type(None):
        return "unset"
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return "table"
    return getattr(annotation, "__name__", str(annotation))


def _literal(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    return f'"{value}"' if isinstance(value, str) else str(value)


def _toml(value: Any) -> str:
    """A default as TOML writes it."""
    if isinstance(value, BaseModel):
        return "{" + ", ".join(f"{k} = {_toml(v)}" for k, v in value.model_dump().items()) + "}"
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {_toml(v)}" for k, v in value.items()) + "}"
    if isinstance(value, list):
        return "[" + ", ".join(_toml(v) for v in value) + "]"
    if value is None:
        return "unset"
    return _literal(value)


def _doc(field: FieldInfo) -> str:
    return " ".join((field.description or "").split())


def _default(field: FieldInfo) -> Any:
    return field.get_default(call_default_factory=True)


def _rows(model: type[BaseModel], prefix: str) -> Iterator[tuple[str, str, str, str]]:
    """(key, type, default, meaning) of every field of ``model``, tables expanded."""
    for name, field in model.model_fields.items():
        key = f"{prefix}{name}"
        subs = _models(field.annotation)
        if len(subs) == 1 and name != "rule":
            yield key, "table", "", _doc(field)
            yield from _rows(subs[0], f"{key}.")
            continue
        typ = _type_name(field.annotation)
        if len(subs) > 1:  # a policy table: its variants by name
            typ = " | ".join(_literal(m.model_fields["rule"].default) for m in subs) + " (table)"
        yield key, typ, _toml(_default(field)), _doc(field)


def _table(rows: list[tuple[str, str, str, str]]) -> list[str]:
    out = ["| key | type | default | meaning |", "|---|---|---|---|"]
    for key, typ, default, doc in rows:
        typ = typ.replace("|", "\\|")
        default = f"`{default}`" if default else ""
        out.append(f"| `{key}` | {typ} | {default} | {doc} |")
    return out


def _variants(model: type[BaseModel], prefix: str) -> list[str]:
    """One table per variant of each policy table of ``model`` (a union of models)."""
    out: list[str] = []
    for name, field in model.model_fields.items():
        subs = _models(field.annotation)
        if len(subs) < 2:
            continue
        for sub in subs:
            rule = sub.model_fields["rule"].default
            out += ["", f'`{prefix}{name} = "{rule}"`: {" ".join((sub.__doc__ or "").split())}']
            rows = [r for r in _rows(sub, f"{prefix}{name}.") if not r[0].endswith(".rule")]
            if rows:
                out += ["", *_table(rows)]
    return out


def configuration_reference() -> str:
    """The markdown page of every setting and learner option."""
    lines = [
        "# Configuration reference",
        "",
        "Every setting of a study and every learner option, with its type, default and meaning.",
        "A settings file (`mpcmobo run --config FILE`) is TOML with any subset of these keys;",
        "an unknown key or an invalid value is refused (exit code 2) with a message naming it.",
        "`DIR/config.toml` of a run holds every value it used. This page is generated from the",
        "docstrings of `mpcmobo.experiment.settings`, `mpcmobo.experiment.sections` and",
        "`mpcmobo.learners.options`.",
        "",
        "## Settings",
        "",
    ]
    top = [r for r in _rows(Settings, "") if not r[0].startswith("learner_options")]
    lines += _table(top)
    lines += [
        "",
        "## Learner options",
        "",
        "A table `[learner_options.NAME]` per learner. A policy table (`deploy`, `optimizer`)",
        "is written as its variant's name when its other fields keep their defaults:",
        '`deploy = "incumbent"`, or in full: `deploy = {rule = "evidence", confidence = 0.95}`.',
    ]
    for name, spec in LEARNER_SPECS.items():
        if spec.options is None:
            continue
        doc = " ".join((spec.options.__doc__ or "").split())
        rows = list(_rows(spec.options, ""))
        lines += ["", f"### `{name}`", "", doc, "", *_table(rows), *_variants(spec.options, "")]
    return "\n".join(lines) + "\n"


def learner_option_lines(name: str) -> list[str]:
    """The options of the learner ``name`` with their defaults, one ``key = value`` each."""
    spec = LEARNER_SPECS[name]
    if spec.options is None:
        return []
    out = []
    for key, field in spec.options.model_fields.items():
        out.append(f"{key} = {_toml(_default(field))}")
    return out
