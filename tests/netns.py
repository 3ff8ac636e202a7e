"""Test hosts as network namespaces: the real daemons as processes, on a real (emulated) network.

Test modules use :data:`requires_netns` (skips, with the reason, where namespaces cannot be
made) and :func:`network_fixture` (one network per module, removed after it). A
:class:`Fleet` starts platforms and stations on hosts of the network with the settings a
deployment on a mesh uses, and talks to them with :func:`rpc` over a socket made inside the
host's namespace (the station's local API answers its own host only, as in the field).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

from brasidas import security
from brasidas.codecs.jsonrpc import encode_request
from brasidas.netem import mesh
from brasidas.netem.netns import BROADCAST, Host, TestNetwork, socket_in, unavailable_reason
from platformd.sim.ax3500 import Ax3500Device, Ax3500Simulator, SimOptions

UNAVAILABLE = unavailable_reason()
requires_netns = pytest.mark.skipif(UNAVAILABLE is not None, reason=UNAVAILABLE or "")
"""Namespace tests skip, saying why, on a machine (or user) that cannot create namespaces."""

SIGNALING_PORT = mesh.SIGNALING_PORT
API_PORT = mesh.API_PORT
MULTICAST_GROUP = mesh.MULTICAST_GROUP


def network_fixture(tag: str) -> Callable[..., Iterator[TestNetwork]]:
    """A module-scoped fixture building one :class:`TestNetwork` for a test module."""

    @pytest.fixture(scope="module")
    def network() -> Iterator[TestNetwork]:
        if UNAVAILABLE is not None:
            pytest.skip(UNAVAILABLE)
        with TestNetwork(tag) as net:
            yield net

    return network


class RpcFailed(Exception):
    def __init__(self, status: int, error: dict[str, Any]) -> None:
        super().__init__(f"HTTP {status}: {error}")
        self.status = status
        self.error = error


async def http_post(
    namespace: str, host: str, port: int, path: str, body: bytes, timeout: float = 10.0
) -> tuple[int, bytes]:
    """POST ``body`` from inside ``namespace``; (status, response body)."""
    sock = socket_in(namespace)
    sock.setblocking(False)
    loop = asyncio.get_running_loop()
    async with asyncio.timeout(timeout):
        try:
            await loop.sock_connect(sock, (host, port))
        except BaseException:
            sock.close()
            raise
        reader, writer = await asyncio.open_connection(sock=sock)
        try:
            writer.write(
                (
                    f"POST {path} HTTP/1.1\r\nHost: {host}:{port}\r\n"
                    f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n"
                    "Connection: close\r\n\r\n"
                ).encode()
                + body
            )
            data = await reader.read()
        finally:
            writer.close()
            await writer.wait_closed()
    head, _, payload = data.partition(b"\r\n\r\n")
    return int(head.split()[1]), payload


async def rpc(namespace: str, host: str, port: int, path: str, method: str, **params: Any) -> Any:
    """One JSON-RPC call over HTTP from inside ``namespace``; raises :class:`RpcFailed`."""
    status, payload = await http_post(
        namespace, host, port, path, encode_request(method, params, 1)
    )
    answer = json.loads(payload) if payload else {}
    if "error" in answer or status != 200:
        raise RpcFailed(status, answer.get("error", {}))
    return answer["result"]


@dataclass
class Daemon:
    host: Host
    name: str
    process: subprocess.Popen[bytes]
    log: Path

    def log_text(self) -> str:
        return self.log.read_text(errors="replace") if self.log.exists() else ""


@dataclass
class Fleet:
    """Daemons on a :class:`TestNetwork`, sharing one fleet key generated for this fleet."""

    net: TestNetwork
    directory: Path
    daemons: list[Daemon] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.directory.mkdir(parents=True, exist_ok=True)
        self.key_file = self.directory / "fleet.key"
        self.key = security.generate_key(self.key_file)

    def _spawn(self, host: Host, name: str, argv: list[str]) -> Daemon:
        log = self.directory / f"{name}.log"
        env = dict(os.environ, XDG_STATE_HOME=str(self.directory / "state" / name))
        env["PYTHONUNBUFFERED"] = "1"
        with log.open("wb") as stderr:
            process = host.spawn([sys.executable, *argv], env=env, stderr=stderr)
        daemon = Daemon(host, name, process, log)
        self.daemons.append(daemon)
        return daemon

    def platform(
        self,
        host: Host,
        platform_id: str,
        *settings: str,
        destinations: tuple[str, ...] = (BROADCAST,),
        sim: bool = True,
    ) -> Daemon:
        """``brasidas-platform`` on ``host`` with a mesh deployment's settings."""
        argv = mesh.platform_argv(
            host.address,
            platform_id,
            str(self.key_file),
            destinations,
            "beacon.max_interval=1.0",
            *settings,
            sim=sim,
        )
        return self._spawn(host, platform_id, argv)

    def station(self, host: Host, station_id: str, *settings: str) -> Daemon:
        """``brasidas-station serve`` on ``host`` (its local API on the host's loopback)."""
        return self._spawn(
            host, station_id, mesh.station_argv(station_id, str(self.key_file), *settings)
        )

    async def wait_listening(
        self, daemon: Daemon, host: str, port: int, timeout: float = 20
    ) -> None:
        """Until ``daemon`` accepts TCP on ``host:port`` inside its namespace."""
        deadline = time.monotonic() + timeout
        while True:
            if daemon.process.poll() is not None:
                raise AssertionError(f"{daemon.name} exited:\n{daemon.log_text()[-3000:]}")
            sock = socket_in(daemon.host.namespace)
            sock.setblocking(False)
            try:
                await asyncio.wait_for(
                    asyncio.get_running_loop().sock_connect(sock, (host, port)), 1
                )
                return
            except (OSError, TimeoutError):
                if time.monotonic() > deadline:
                    raise AssertionError(
                        f"{daemon.name} not listening on {host}:{port}:\n{daemon.log_text()[-3000:]}"
                    ) from None
                await asyncio.sleep(0.1)
            finally:
                sock.close()

    async def api(self, station: Daemon, method: str, **params: Any) -> Any:
        """The station daemon's local API, from its own host."""
        return await rpc(
            station.host.namespace, "127.0.0.1", API_PORT, "/api/rpc", method, **params
        )

    async def connect(self, station: Daemon, platform_id: str, timeout: float = 30) -> None:
        """Until ``station`` holds a session with ``platform_id`` (once it is discovered)."""

        async def connected() -> bool:
            try:
                await self.api(station, "connect", platform_id=platform_id)
            except RpcFailed:
                return False
            return True

        await wait_for(connected, timeout, step=0.3)

    async def engage(self, station: Daemon, platform_id: str) -> bool:
        """Ask for the manual override once; whether it was acknowledged."""
        try:
            answer = await self.api(station, "movrd", platform_id=platform_id, engaged=True)
        except RpcFailed:
            return False
        return bool(answer.get("accepted"))

    def stop(self) -> None:
        for daemon in self.daemons:
            if daemon.process.poll() is None:
                daemon.process.terminate()
        for daemon in self.daemons:
            try:
                daemon.process.wait(10)
            except subprocess.TimeoutExpired:
                daemon.process.kill()
                daemon.process.wait()
        self.daemons.clear()


async def wait_for(
    predicate: Callable[[], Any],
    timeout: float = 10.0,
    step: float = 0.05,
    *,
    state: Callable[[], Any] | None = None,
) -> Any:
    """Await an async or sync ``predicate`` until truthy; its value. Fails after ``timeout``,
    saying what ``state()`` (sync or async) returns then: what the test saw instead."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if asyncio.iscoroutine(value):
            value = await value
        if value:
            return value
        if time.monotonic() > deadline:
            message = f"condition not met within {timeout} s"
            if state is not None:
                try:
                    seen = state()
                    if asyncio.iscoroutine(seen):
                        seen = await seen
                except Exception as error:  # the state's own RPC may fail over a cut link
                    seen = f"(state unavailable: {error!r})"
                message += f": {seen}"
            raise AssertionError(message)
        await asyncio.sleep(step)


def udp_socket_in(namespace: str, bind: tuple[str, int] | None = None) -> socket.socket:
    sock = socket_in(namespace, socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
    if bind is not None:
        sock.bind(bind)
    return sock


async def open_session(
    namespace: str, address: str, platform_id: str, key: bytes, station_id: str = "probe"
) -> str:
    """Authenticate to the platform at ``address`` as a station would; the session token."""
    challenge = await rpc(namespace, address, SIGNALING_PORT, "/rpc", "challenge")
    nonce, station_nonce = str(challenge["nonce"]), os.urandom(16).hex()
    proof = security.connect_proof(key, platform_id, station_id, nonce, station_nonce)
    answer = await rpc(
        namespace,
        address,
        SIGNALING_PORT,
        "/rpc",
        "connect",
        station_id=station_id,
        nonce=nonce,
        station_nonce=station_nonce,
        proof=proof,
    )
    return str(answer["session"])


QUIET = (
    "gps.enabled=false",
    "imu.enabled=false",
    "navcam.enabled=false",
    "audio.enabled=false",
)
"""Settings for a platform that only advertises and answers (lighter, faster to start)."""


class ControllerThread:
    """A simulated AX3500 on a pty, on a thread and event loop of its own, for a platform
    process to open as ``motor.port``; it logs each motor output change with its time."""

    def __init__(self) -> None:
        self.outputs: list[tuple[float, float, float]] = []
        """(time.monotonic(), speed, turn) at each change of the controller's outputs."""
        self.path = ""
        self.device: Ax3500Device | None = None
        self._ready = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._thread = threading.Thread(target=self._main, name="ax3500-sim", daemon=True)

    def start(self) -> None:
        self._thread.start()
        if not self._ready.wait(10):
            raise RuntimeError("simulated controller did not start")

    def close(self) -> None:
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        self._thread.join(10)

    def commands(self) -> list[str]:
        """The command lines the controller received, in order (its own log)."""
        return list(self.device.received) if self.device is not None else []

    def _main(self) -> None:
        asyncio.run(self._serve())

    async def _serve(self) -> None:
        self._loop = asyncio.get_running_loop()
        self._stop = asyncio.Event()
        simulator = Ax3500Simulator(SimOptions(), record=True)
        device = self.device = simulator.device

        def record(speed: float, turn: float) -> None:
            self.outputs.append((time.monotonic(), speed, turn))

        device.on_output = record
        simulator.start()
        self.path = simulator.path
        self._ready.set()
        try:
            await self._stop.wait()
        finally:
            simulator.close()


def speed_commands(lines: list[str]) -> list[int]:
    """The signed channel-1 (speed) values of ``!A``/``!a`` commands, in order."""
    values = []
    for line in lines:
        if len(line) >= 4 and line[:2] in ("!A", "!a"):
            with contextlib.suppress(ValueError):
                value = int(line[2:4], 16)
                values.append(value if line[1] == "A" else -value)
    return values


def percentile(values: list[float], share: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, max(0, round(share * (len(ordered) - 1))))]
