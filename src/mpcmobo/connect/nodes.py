"""The node map of a plant reached over OPC UA (``nodes.toml``) and its security settings.

Every state and input of the system maps to a NodeId; a node holds ``scale * value + offset``
in the plant's units (the model's value is ``(node - offset) / scale``). Everything else in the
file is in the model's units: ``safe_input``, the input the tool writes when it lets go of the
plant, must lie within the system's input bounds. ``enable`` is the operator's permissive node
(the tool writes only while it reads true), ``heartbeat`` a node the tool writes a counter to
in every write, so the plant's own watchdog can take over when the counter stops. Credentials
come from the ``[security]`` table or the ``MPCMOBO_OPCUA_*`` environment variables (the
environment wins); they are held as secrets and never printed or recorded.
"""

from __future__ import annotations

import os
import tomllib
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    SecretStr,
    ValidationError,
    field_validator,
    model_validator,
)

from mpcmobo.systems.base import System

__all__ = ["ENV", "ConnectError", "NodeMap", "PlantNode", "Security", "load_nodes"]

# the environment variables of the security settings, by field
ENV = {
    "user": "MPCMOBO_OPCUA_USER",
    "password": "MPCMOBO_OPCUA_PASSWORD",
    "certificate": "MPCMOBO_OPCUA_CERTIFICATE",
    "private_key": "MPCMOBO_OPCUA_PRIVATE_KEY",
    "private_key_password": "MPCMOBO_OPCUA_PRIVATE_KEY_PASSWORD",
    "server_certificate": "MPCMOBO_OPCUA_SERVER_CERTIFICATE",
    "policy": "MPCMOBO_OPCUA_POLICY",
    "mode": "MPCMOBO_OPCUA_MODE",
}


class ConnectError(ValueError):
    """A node map, a server or a plant the tool cannot work with; the message says what is
    wrong. Nothing recorded is changed (exit code 2 on the command line)."""


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class PlantNode(_Strict):
    """One state's or input's node: its NodeId and the unit conversion
    ``node = scale * value + offset``."""

    node: str = Field(min_length=1)
    scale: float = Field(1.0, allow_inf_nan=False)
    offset: float = Field(0.0, allow_inf_nan=False)

    @field_validator("scale")
    @classmethod
    def _nonzero(cls, v: float) -> float:
        if v == 0:
            raise ValueError("scale cannot be 0")
        return v


class Security(_Strict):
    """How the client identifies itself: a user and password, and/or a certificate and private
    key with a security policy and mode (asyncua's ``set_security``). Paths are read by asyncua;
    secrets stay :class:`~pydantic.SecretStr`."""

    user: str | None = None
    password: SecretStr | None = None
    certificate: Path | None = None
    private_key: Path | None = None
    private_key_password: SecretStr | None = None
    server_certificate: Path | None = None
    policy: Literal["Basic256Sha256", "Aes128Sha256RsaOaep", "Aes256Sha256RsaPss"] | None = None
    mode: Literal["Sign", "SignAndEncrypt"] = "SignAndEncrypt"

    @model_validator(mode="after")
    def _complete(self) -> Security:
        given = [k for k in ("certificate", "private_key") if getattr(self, k) is not None]
        if self.policy is not None and len(given) < 2:
            raise ValueError(f"policy {self.policy} needs a certificate and a private_key")
        if self.policy is None and given:
            raise ValueError(f"a {given[0]} needs a policy (Basic256Sha256, ...)")
        return self

    @property
    def encrypted(self) -> bool:
        """Whether the secure channel signs (and encrypts) with a certificate."""
        return self.policy is not None


class NodeMap(_Strict):
    """The contents of ``nodes.toml`` (module docstring)."""

    states: dict[str, PlantNode]
    """Every state of the system: a NodeId, or a table ``{node, scale, offset}``."""
    inputs: dict[str, PlantNode]
    """Every input of the system, as the states."""
    safe_input: dict[str, float]
    """The input (model units, within its bounds) written when the tool lets go of the plant."""
    enable: str | None = None
    """The operator's permissive (boolean) node: the tool writes only while it is true."""
    heartbeat: str | None = None
    """An integer node the tool writes a counter to with every write (the plant's watchdog)."""
    stale_periods: int = Field(3, ge=1, le=1000)
    """A state whose source timestamp has not advanced for this many periods is stale."""
    solve_budget: float = Field(0.5, gt=0, le=0.9)
    """The fraction of the period a solve may take before the previous plan's input is used."""
    reconnect_timeout: float = Field(30.0, ge=0, allow_inf_nan=False)
    """Seconds to try to reach the server again after a lost connection (to write the safe
    input)."""
    timeout: float = Field(4.0, gt=0, allow_inf_nan=False)
    """Seconds a request waits for the server's answer."""
    security: Security = Field(default_factory=Security)
    """The client's credentials (also from the environment)."""

    @field_validator("states", "inputs", mode="before")
    @classmethod
    def _nodes(cls, v: Any) -> Any:
        if isinstance(v, dict):
            return {k: {"node": n} if isinstance(n, str) else n for k, n in v.items()}
        return v

    def check(self, system: System) -> NodeMap:
        """The map, checked against ``system``: every state and input mapped, no other name,
        the safe input within the input bounds."""
        for kind, names, mapped in (
            ("states", system.state_names, self.states),
            ("inputs", system.input_names, self.inputs),
            ("safe_input", system.input_names, self.safe_input),
        ):
            missing = [n for n in names if n not in mapped]
            extra = [n for n in mapped if n not in names]
            if missing or extra:
                what = f"has no {missing[0]!r}" if missing else f"names {extra[0]!r}"
                raise ConnectError(
                    f"nodes: [{kind}] {what}; the system {system.name} has the "
                    f"{'states' if kind == 'states' else 'inputs'} {list(names)}"
                )
        u = self.safe(system)
        bad = np.flatnonzero((u < system.u_lb) | (u > system.u_ub))
        if bad.size:
            j = int(bad[0])
            raise ConnectError(
                f"nodes: safe_input {system.input_names[j]} = {u[j]:g} is outside its bounds "
                f"[{system.u_lb[j]:g}, {system.u_ub[j]:g}]"
            )
        return self

    def safe(self, system: System) -> np.ndarray:
        """The safe input as a vector in the system's input order (model units)."""
        return np.array([self.safe_input[n] for n in system.input_names], float)


def _from_env(table: dict[str, Any]) -> dict[str, Any]:
    """The ``[security]`` table with the environment's values over it."""
    out = dict(table)
    for key, var in ENV.items():
        value = os.environ.get(var)
        if value:
            out[key] = value
    return out


def load_nodes(path: str | Path, system: System) -> NodeMap:
    """The node map of ``path`` (TOML), checked against ``system``; a :class:`ConnectError`
    names what is wrong (never a secret's value)."""
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConnectError(f"the node map {path} does not exist") from None
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as err:
        raise ConnectError(f"the node map {path} cannot be read: {err}") from None
    data["security"] = _from_env(data.get("security", {}))
    try:
        nodes = NodeMap.model_validate(data)
    except ValidationError as err:
        raise ConnectError(f"{_node_error(err.errors()[0])} ({path})") from None
    return nodes.check(system)


def _node_error(first: Any) -> str:
    """The first problem of a node map: its key and pydantic's message, never the input (a
    password in the wrong place stays unprinted); an unknown key with the keys allowed there."""
    loc = tuple(str(p) for p in first["loc"])
    where = ".".join(loc)
    if first["type"] != "extra_forbidden":
        return f"nodes: {where}: {first['msg']}"
    tables: dict[tuple[str, ...], type[BaseModel]] = {(): NodeMap, ("security",): Security}
    model = PlantNode if loc[0] in ("states", "inputs") else tables.get(loc[:-1])
    allowed = f"; allowed keys here: {', '.join(model.model_fields)}" if model else ""
    return f"nodes: {where}: unknown key{allowed}"
