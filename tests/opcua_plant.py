"""A simulated plant behind a real OPC UA server (asyncua) on localhost, for the tests of
``mpcmobo connect`` and benchmarks/connect_latency.py.

The server runs in a thread of its own with its own event loop. Every ``period`` seconds it
publishes the states with a new source timestamp (the temperature ``T`` in degrees Celsius, as
a plant's historian would). The plant takes one step of the system's true model
(``System.plant_step``, its sampling time ``dt`` played ``dt / period`` times faster) with the
inputs its nodes hold either on that clock too (``lockstep=False``: a real-time plant, whose
step and the client's write race when the machine is busy) or at each write of the inputs
(``lockstep=True``: every period's input acts for exactly one step however late the client
runs, for the tests whose subject is not the timing). Every write a client makes is recorded
(``writes``). Faults to inject: ``freeze`` (the states stop updating: stale), ``fail_sensor``
(a bad status code), ``set_enable(False)``, ``refuse_writes`` (the inputs become read-only),
``outage(seconds)`` (the network goes away: the connections close, the port refuses new ones,
the plant runs on), and ``interrupt_after`` (a Ctrl-C in the main thread at a given write).
"""

from __future__ import annotations

import _thread
import asyncio
import signal
import socket
import threading
import time
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import numpy as np
from asyncua import Server, ua
from asyncua.common.callback import CallbackType
from asyncua.server.user_managers import UserManager

NS = "urn:mpcmobo:test-plant"
KELVIN = 273.15


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def node_map(password_env: bool = False, **extra: Any) -> str:
    """nodes.toml for the simulated CSTR (namespace index 2)."""
    lines = [
        'enable = "ns=2;s=CSTR.Enable"',
        'heartbeat = "ns=2;s=CSTR.Heartbeat"',
        *(f"{k} = {v!r}" for k, v in extra.items()),
        "[states]",
        'V = "ns=2;s=CSTR.V"',
        'Ca = "ns=2;s=CSTR.Ca"',
        f'T = {{ node = "ns=2;s=CSTR.T", offset = {-KELVIN} }}',
        "[inputs]",
        'qs = "ns=2;s=CSTR.qs"',
        'qc = "ns=2;s=CSTR.qc"',
        "[safe_input]",
        "qs = 100.0",
        "qc = 110.0",
    ]
    if password_env:
        lines += ["[security]", 'user = "operator"']
    return "\n".join(lines) + "\n"


async def make_certificate(key: Path, cert: Path, app_uri: str, server: bool = False) -> None:
    """A self-signed certificate and its private key for ``app_uri``."""
    from asyncua.crypto.cert_gen import setup_self_signed_certificate
    from cryptography.x509.oid import ExtendedKeyUsageOID

    use = ExtendedKeyUsageOID.SERVER_AUTH if server else ExtendedKeyUsageOID.CLIENT_AUTH
    await setup_self_signed_certificate(
        key, cert, app_uri, socket.gethostname(), [use], {"commonName": app_uri}
    )


class _Users(UserManager):
    """Only ``operator`` with the given password may open a session."""

    def __init__(self, password: str) -> None:
        self.password = password

    def get_user(
        self, iserver: Any, username: Any = None, password: Any = None, certificate: Any = None
    ) -> Any:
        from asyncua.crypto.permission_rules import User, UserRole

        if username == "operator" and password == self.password:
            return User(role=UserRole.Admin)
        return None


class SimPlant:
    """The simulated plant and its server (module docstring)."""

    def __init__(
        self,
        system: Any,
        x0: Any,
        period: float,
        password: str | None = None,
        certificates: Path | None = None,
        lockstep: bool = False,
    ) -> None:
        """``password``: only the user ``operator`` with it may connect; ``certificates``: a
        directory for the server's certificate (made there): only Basic256Sha256 with
        SignAndEncrypt is offered; ``lockstep``: the plant steps at each write of the inputs
        instead of on the clock (module docstring)."""
        self.system, self.period, self.password = system, period, password
        self.lockstep = lockstep
        self.certificates = certificates
        self.x0 = np.asarray(x0, float).copy()
        self.x = self.x0.copy()
        self.u = np.asarray(system.u_ref, float).copy()
        self.port = free_port()
        self.url = f"opc.tcp://127.0.0.1:{self.port}/mpcmobo/"
        self.writes: list[tuple[str, Any]] = []
        self.requests = 0  # write requests of clients
        self.frozen = False
        self.sensor_failed = False
        self.enable = True
        self.read_only = False
        self.interrupt_at: int | None = None
        self.published = 0
        self._server: Server | None = None
        self._ready = threading.Event()
        self._stop: asyncio.Event | None = None
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, daemon=True)
        self._thread.start()
        self.call(self._start())
        self._stepper = asyncio.run_coroutine_threadsafe(self._step_loop(), self.loop)

    # ------------------------------------------------------------------ control
    def call(self, coro: Any, timeout: float = 20.0) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def close(self) -> None:
        self._stepper.cancel()
        self.call(self._shutdown())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(5)

    def reset(self) -> None:
        """Back to the start: no fault, no write recorded, the state ``x0`` again."""
        self.frozen, self.sensor_failed, self.interrupt_at = False, False, None
        self.x = np.asarray(self.x0, float).copy()
        self.u = np.asarray(self.system.u_ref, float).copy()
        self.set_enable(True)
        self.refuse_writes(False)
        self.call(self._inputs())
        self.writes.clear()

    def freeze(self, frozen: bool = True) -> None:
        self.frozen = frozen

    def fail_sensor(self, failed: bool = True) -> None:
        """The volume's sensor reports BadSensorFailure (from its next publication)."""
        self.sensor_failed = failed

    def set_enable(self, on: bool) -> None:
        self.enable = on
        self.call(self._publish())

    def refuse_writes(self, refuse: bool = True) -> None:
        self.read_only = refuse
        self.call(self._access())

    def outage(self, seconds: float) -> Any:
        """The server goes away now and comes back after ``seconds`` (not waited for)."""
        return asyncio.run_coroutine_threadsafe(self._outage(seconds), self.loop)

    def interrupt_after(self, n_requests: int, signum: int = signal.SIGINT) -> None:
        """A Ctrl-C (or the signal ``signum``) in the main thread at the ``n_requests``-th
        write request from now."""
        self.interrupt_at = self.requests + n_requests
        self.interrupt_signal = signum

    def after_writes(self, n_requests: int, fault: Any) -> threading.Thread:
        """Call ``fault()`` (in a thread of its own) once ``n_requests`` more write requests
        have come."""
        target = self.requests + n_requests

        def wait() -> None:
            while self.requests < target:
                time.sleep(0.005)
            fault()

        thread = threading.Thread(target=wait, daemon=True)
        thread.start()
        return thread

    def input_writes(self, name: str) -> np.ndarray:
        return np.array([v for node, v in self.writes if node == f"CSTR.{name}"], float)

    def wait_published(self, n: int, timeout: float = 10.0) -> None:
        """Wait until the states have been published ``n`` more times."""
        end, target = time.monotonic() + timeout, self.published + n
        while self.published < target and time.monotonic() < end:
            time.sleep(0.01)

    # ------------------------------------------------------------------ server side
    async def _start(self) -> None:
        server = Server(user_manager=_Users(self.password) if self.password else None)
        await server.init()
        server.set_endpoint(self.url)
        if self.password:
            server.set_security_IDs(["Username"])
        if self.certificates is not None:
            key, cert = self.certificates / "server-key.pem", self.certificates / "server-cert.der"
            await make_certificate(key, cert, "urn:freeopcua:python:server", server=True)
            await server.load_certificate(str(cert))
            await server.load_private_key(str(key))
            server.set_security_policy([ua.SecurityPolicyType.Basic256Sha256_SignAndEncrypt])
        idx = await server.register_namespace(NS)
        assert idx == 2
        obj = await server.nodes.objects.add_object(idx, "CSTR")
        self._nodes: dict[str, Any] = {}
        for name in (*self.system.state_names, *self.system.input_names):
            self._nodes[name] = await obj.add_variable(
                ua.NodeId(f"CSTR.{name}", idx), name, ua.Variant(0.0, ua.VariantType.Double)
            )
        self._nodes["Enable"] = await obj.add_variable(
            ua.NodeId("CSTR.Enable", idx), "Enable", ua.Variant(True, ua.VariantType.Boolean)
        )
        self._nodes["Heartbeat"] = await obj.add_variable(
            ua.NodeId("CSTR.Heartbeat", idx), "Heartbeat", ua.Variant(0, ua.VariantType.Int32)
        )
        for name in (*self.system.input_names, "Heartbeat"):
            await self._nodes[name].set_writable()
        server.subscribe_server_callback(CallbackType.PostWrite, self._written)
        await server.start()
        self._server = server
        await self._inputs()
        await self._access()
        await self._publish()

    async def _inputs(self) -> None:
        for j, name in enumerate(self.system.input_names):
            await self._set(name, float(self.u[j]))

    async def _shutdown(self) -> None:
        server, self._server = self._server, None
        if server is not None:
            await server.stop()

    async def _outage(self, seconds: float) -> None:
        """The network goes away (every connection closed, none accepted), the plant runs on."""
        assert self._server is not None and self._server.bserver is not None
        await self._server.bserver.stop()
        await asyncio.sleep(seconds)
        await self._server.bserver.start()

    async def _access(self) -> None:
        if self._server is None:
            return
        for name in self.system.input_names:
            if self.read_only:
                await self._nodes[name].set_read_only()
            else:
                await self._nodes[name].set_writable()

    async def _set(self, name: str, value: Any, vtype: Any = ua.VariantType.Double) -> None:
        now = datetime.now(UTC)
        dv = ua.DataValue(ua.Variant(value, vtype), SourceTimestamp=now, ServerTimestamp=now)
        if name == "V" and self.sensor_failed:
            dv.StatusCode = ua.StatusCode(ua.StatusCodes.BadSensorFailure)
        assert self._server is not None
        await self._server.write_attribute_value(self._nodes[name].nodeid, dv)

    async def _publish(self) -> None:
        if self._server is None:
            return
        for j, name in enumerate(self.system.state_names):
            value = self.x[j] - KELVIN if name == "T" else self.x[j]
            await self._set(name, float(value))
        await self._set("Enable", self.enable, ua.VariantType.Boolean)
        self.published += 1

    async def _step_loop(self) -> None:
        t0 = time.monotonic()
        k = 0
        while True:
            k += 1
            await asyncio.sleep(max(0.0, t0 + k * self.period - time.monotonic()))
            if self._server is None or self.frozen:
                continue
            if not self.lockstep:
                await self._step()
            await self._publish()

    async def _step(self) -> None:
        """One step of the plant with the inputs its nodes hold."""
        for j, name in enumerate(self.system.input_names):
            self.u[j] = await self._nodes[name].read_value()
        self.x = np.asarray(self.system.plant_step(self.x, self.u), float)

    async def _written(self, event: Any, dispatcher: Any) -> None:
        if not event.is_external:  # the server's own writes (its status, the plant's states)
            return
        written = [
            (wv.NodeId.Identifier, wv.Value.Value.Value) for wv in event.request_params.NodesToWrite
        ]
        self.writes.extend(written)
        self.requests += 1
        inputs = {f"CSTR.{name}" for name in self.system.input_names}
        if self.lockstep and not self.frozen and inputs & {node for node, _ in written}:
            await self._step()
            await self._publish()
        if self.interrupt_at is not None and self.requests >= self.interrupt_at:
            self.interrupt_at = None
            _thread.interrupt_main(self.interrupt_signal)
