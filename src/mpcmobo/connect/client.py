"""The plant's OPC UA client, on ``asyncua``: one batched read and one batched write per period.

:class:`PlantClient` reads the states and the enable node in one ``Read`` service call (a
value, its status and its source timestamp per node) and writes the inputs and the heartbeat
in one ``Write`` call, each value with the variant type its node holds. A failed call is a
:class:`ConnectionLost`; a bad status on a state, a refused write or a withdrawn enable is a
:class:`PlantFault` of its kind. With ``dry_run`` nothing is ever written. ``asyncua`` is the
optional extra ``opcua`` (``pip install "mpcmobo[opcua]"``).
"""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass
from datetime import datetime
from typing import Any
from urllib.parse import urlsplit, urlunsplit

import numpy as np

from mpcmobo.connect.nodes import ConnectError, NodeMap
from mpcmobo.systems.base import System

__all__ = ["ConnectionLost", "PlantClient", "PlantFault", "Reading", "public_url"]


class PlantFault(Exception):
    """The plant stops a trial: ``kind`` is ``connection``, ``stale``, ``quality``,
    ``refused`` or ``enable``; the message says what happened."""

    def __init__(self, kind: str, message: str) -> None:
        super().__init__(message)
        self.kind = kind


class ConnectionLost(PlantFault):
    """A read or a write to the server failed: the connection is gone."""

    def __init__(self, message: str) -> None:
        super().__init__("connection", message)


@dataclass(frozen=True)
class Reading:
    """One batched read: the state ``x`` (model units), each state's source timestamp (None
    where the server gives none) and whether the operator's enable is on."""

    x: np.ndarray
    stamps: tuple[datetime | None, ...]
    enabled: bool


def public_url(url: str) -> str:
    """``url`` without the user and password it may carry (what may be printed or recorded)."""
    parts = urlsplit(url)
    host = parts.netloc.rpartition("@")[2]
    return urlunsplit((parts.scheme, host, parts.path, parts.query, parts.fragment))


def _ua() -> Any:
    """asyncua's ``ua`` module, or a :class:`ConnectError` saying how to install it."""
    try:
        from asyncua import ua
    except ImportError:
        raise ConnectError(
            'connecting to a plant needs asyncua: pip install "mpcmobo[opcua]"'
        ) from None
    return ua


class PlantClient:
    """A session with the plant's OPC UA server at ``url`` for the nodes of ``nodes``."""

    def __init__(self, url: str, nodes: NodeMap, system: System, dry_run: bool = False) -> None:
        self.url, self.nodes, self.system, self.dry_run = url, nodes, system, dry_run
        self._client: Any = None
        self._beat = 0
        self._types: list[Any] = []

    # ------------------------------------------------------------------ session
    async def open(self) -> None:
        """Connect and check every node once; a :class:`ConnectError` names what fails."""
        ua = _ua()
        from asyncua import Client

        client = Client(self.url, timeout=self.nodes.timeout)
        try:
            await self._secure(client)
            await asyncio.wait_for(client.connect(), self.nodes.timeout * 2)
        except (TimeoutError, OSError, ua.UaError) as err:
            await self._drop(client)
            raise ConnectError(
                f"cannot connect to the OPC UA server at {public_url(self.url)}: "
                f"{type(err).__name__}: {err or 'no answer'}"
            ) from None
        self._client = client
        try:
            self._reads = [client.get_node(n.node) for n in self.nodes.states.values()]
            if self.nodes.enable is not None:
                self._reads.append(client.get_node(self.nodes.enable))
            self._writes = [client.get_node(n.node) for n in self.nodes.inputs.values()]
            if self.nodes.heartbeat is not None:
                self._writes.append(client.get_node(self.nodes.heartbeat))
        except (ValueError, ua.UaError) as err:
            await self.close()
            raise ConnectError(f"nodes: a NodeId cannot be parsed: {err}") from None
        await self._check_nodes(ua)

    async def _secure(self, client: Any) -> None:
        """The client's identity from the node map's security settings."""
        sec = self.nodes.security
        if sec.user is not None:
            client.set_user(sec.user)
        if sec.password is not None:
            client.set_password(sec.password.get_secret_value())
        if sec.encrypted:
            from asyncua import ua
            from asyncua.crypto import security_policies

            for key in ("certificate", "private_key", "server_certificate"):
                path = getattr(sec, key)
                if path is not None and not path.is_file():
                    raise ConnectError(f"security: the {key} file {path} does not exist")
            key_password = sec.private_key_password
            await client.set_security(
                getattr(security_policies, f"SecurityPolicy{sec.policy}"),
                str(sec.certificate),
                str(sec.private_key),
                None if key_password is None else key_password.get_secret_value(),
                None if sec.server_certificate is None else str(sec.server_certificate),
                getattr(ua.MessageSecurityMode, sec.mode),
            )

    async def _check_nodes(self, ua: Any) -> None:
        """Every node readable, the written ones' variant types learned."""
        names = [*self.nodes.states, *(["enable"] if self.nodes.enable else [])]
        names_w = [*self.nodes.inputs, *(["heartbeat"] if self.nodes.heartbeat else [])]
        try:
            values = await self._client.read_attributes([*self._reads, *self._writes])
        except (TimeoutError, OSError, ua.UaError) as err:
            await self.close()
            raise ConnectError(f"the server does not answer a read: {err}") from None
        for name, node, dv in zip([*names, *names_w], [*self._reads, *self._writes], values):
            if not dv.StatusCode.is_good() or dv.Value is None or dv.Value.Value is None:
                await self.close()
                raise ConnectError(
                    f"nodes: {name} ({node.nodeid.to_string()}) cannot be read: "
                    f"{dv.StatusCode.name}"
                )
        self._types = [dv.Value.VariantType for dv in values[len(self._reads) :]]
        for name, vtype in zip(self.nodes.inputs, self._types):
            kind = getattr(vtype, "name", str(vtype))
            if kind not in NUMERIC_TYPES:
                await self.close()
                raise ConnectError(
                    f"nodes: input {name} ({self.nodes.inputs[name].node}) is a {kind} node; "
                    "an input needs a number node (Float or Double; an integer node rounds "
                    "what is written, and the log records the rounded value)"
                )
        if self.nodes.heartbeat is not None:
            beat = values[-1].Value.Value
            self._beat = int(beat) if not isinstance(beat, bool) else 0

    async def close(self) -> None:
        """End the session (quietly if the server is gone)."""
        client, self._client = self._client, None
        await self._drop(client)

    @staticmethod
    async def _drop(client: Any) -> None:
        if client is None:
            return
        try:
            await asyncio.wait_for(client.disconnect(), 2.0)
        except Exception:  # noqa: BLE001, S110 - a dead connection has nothing left to close
            pass

    # ------------------------------------------------------------------ read and write
    async def read(self) -> Reading:
        """The states and the enable node, in one call."""
        ua = _ua()
        if self._client is None:
            raise ConnectionLost("not connected to the server")
        try:
            values = await self._client.read_attributes(self._reads, ua.AttributeIds.Value)
        except (TimeoutError, OSError, ua.UaError) as err:
            raise ConnectionLost(
                f"reading the states failed: {type(err).__name__}: {err}"
            ) from None
        x: dict[str, float] = {}
        stamps: dict[str, datetime | None] = {}
        for dv, (name, node) in zip(values, self.nodes.states.items()):
            if not dv.StatusCode.is_good() or dv.Value is None:
                raise PlantFault("quality", f"state {name} reads {dv.StatusCode.name}")
            x[name] = (_number(dv.Value.Value, name) - node.offset) / node.scale
            stamps[name] = dv.SourceTimestamp or dv.ServerTimestamp
        enabled = True
        if self.nodes.enable is not None:
            dv = values[-1]
            enabled = dv.StatusCode.is_good() and dv.Value is not None and bool(dv.Value.Value)
        names = self.system.state_names
        return Reading(np.array([x[n] for n in names]), tuple(stamps[n] for n in names), enabled)

    async def write(self, u: np.ndarray, beat: bool = True) -> np.ndarray:
        """Write the input ``u`` (model units, the system's order) and (``beat``) the next
        heartbeat in one call; the input as written (model units: an integer node's rounding
        undone, so that the log holds what the plant got). A refused value is a
        :class:`PlantFault` (``refused``). The safe input goes without a beat: once the tool
        lets go, the heartbeat stops, and a plant's watchdog takes over."""
        if self.dry_run:
            return np.asarray(u, float)
        ua = _ua()
        by_name = dict(zip(self.system.input_names, np.asarray(u, float)))
        values = [n.scale * by_name[name] + n.offset for name, n in self.nodes.inputs.items()]
        if self.nodes.heartbeat is not None and beat:
            self._beat = (self._beat + 1) % 2**31
            values.append(self._beat)
        cast = [_cast(v, t) for v, t in zip(values, self._types)]
        dvs = [ua.DataValue(ua.Variant(v, t)) for v, t in zip(cast, self._types)]
        if self._client is None:
            raise ConnectionLost("not connected to the server")
        try:
            results = await self._client.write_values(
                self._writes[: len(dvs)], dvs, raise_on_partial_error=False
            )
        except (TimeoutError, OSError, ua.UaError) as err:
            raise ConnectionLost(
                f"writing the inputs failed: {type(err).__name__}: {err}"
            ) from None
        names = [*self.nodes.inputs, "heartbeat"]
        for name, status in zip(names, results):
            if not status.is_good():
                raise PlantFault(
                    "refused", f"the server refused the write of {name}: {status.name}"
                )
        written = {
            name: (float(v) - n.offset) / n.scale
            for (name, n), v in zip(self.nodes.inputs.items(), cast)
        }
        return np.array([written[name] for name in self.system.input_names])


def _number(value: Any, name: str) -> float:
    """A state's value as a finite float, else a :class:`PlantFault` (``quality``)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        v = math.nan
    if isinstance(value, bool) or not math.isfinite(v):
        raise PlantFault("quality", f"state {name} reads {value!r}, not a finite number")
    return v


# the variant types an input node may have: numbers (an integer one rounds the value)
NUMERIC_TYPES = frozenset(
    {"Float", "Double", "Byte", "SByte", "Int16", "UInt16", "Int32", "UInt32", "Int64", "UInt64"}
)


def _cast(value: float, vtype: Any) -> Any:
    """``value`` as the Python type of the node's variant type."""
    name = getattr(vtype, "name", "")
    if name == "Boolean":
        return bool(int(value) % 2)
    if "Int" in name or name == "Byte":
        return int(round(value))
    return float(value)
