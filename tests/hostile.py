"""A hostile mesh (issue 19): a platform, the station holding control, an observer station, and
an attacker host without the fleet key, as network namespaces on one bridge (tests/netns.py).

The holder sits behind a link emulator, so a test can cut its link and see what it sent
(:class:`Capture`: a listener recording the air); the attacker (:class:`Attacker`) sends what it
likes, from any source address it likes (a raw socket: the spoofing a host on the same segment
can do), recorded datagrams included (:meth:`Attacker.replay`). Test modules
build one :class:`HostileRig` per module with :func:`hostile_rig_fixture`.
"""

from __future__ import annotations

import asyncio
import json
import socket
import struct
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from netns import API_PORT, Daemon, Fleet, RpcFailed, http_post, wait_for

from brasidas.codecs.jsonrpc import encode_request
from brasidas.netem.netns import Host, TestNetwork, socket_in
from brasidas.netem.relay import Datagram, parse

PLATFORM = "rover-h"
VELOCITY_PORT = 21001
"""The platform's ``$PVEL`` port (velocity.port's default, as deployed)."""
PLATFORM_SETTINGS = (
    "gps.enabled=false",
    "imu.enabled=false",
    "audio.enabled=false",
    "sim.demo_map=false",
    # A small NavCam: a few hundred datagrams per test, light on a loaded machine.
    "navcam.width=160",
    "navcam.height=120",
    "navcam.framerate=10",
    "navcam.idle_framerate=10",
)


class Capture:
    """What a link emulator carried, parsed: (direction, time, datagram). Its :meth:`tap` runs
    on the emulator's thread."""

    def __init__(self) -> None:
        self.seen: list[tuple[str, float, Datagram]] = []

    def tap(self, direction: str, frame: bytes, now: float) -> None:
        datagram = parse(frame)
        if datagram is not None:
            self.seen.append((direction, now, datagram))

    def select(
        self, direction: str, protocol: str, port: int, *, source: bool = False
    ) -> list[tuple[float, Datagram]]:
        return [
            (now, d)
            for seen_direction, now, d in list(self.seen)
            if seen_direction == direction
            and d.protocol == protocol
            and (d.source[1] if source else d.destination[1]) == port
            and d.payload
        ]


def spoofed_udp(source: tuple[str, int], destination: tuple[str, int], payload: bytes) -> bytes:
    """An IPv4 packet carrying one UDP datagram from ``source`` (any address) to
    ``destination``; the kernel fills in the IP checksum (the UDP one is left out, as IPv4
    allows)."""
    header = struct.pack(
        "!BBHHHBBH4s4s",
        0x45,  # IPv4, 5-word header
        0,
        20 + 8 + len(payload),
        0,  # identification: the kernel's
        0x4000,  # don't fragment
        64,
        socket.IPPROTO_UDP,
        0,
        socket.inet_aton(source[0]),
        socket.inet_aton(destination[0]),
    )
    udp = struct.pack("!HHHH", source[1], destination[1], 8 + len(payload), 0)
    return header + udp + payload


class Attacker:
    """A host on the mesh without the fleet key; it can put any source address on a datagram."""

    def __init__(self, host: Host) -> None:
        self.host = host
        self.sent = 0
        self._raw: socket.socket | None = None

    def send_as(
        self, source: tuple[str, int], destination: tuple[str, int], payload: bytes
    ) -> None:
        """One UDP datagram to ``destination`` that claims to come from ``source``."""
        if self._raw is None:
            self._raw = socket_in(
                self.host.namespace, socket.AF_INET, socket.SOCK_RAW, socket.IPPROTO_RAW
            )
        self._raw.sendto(spoofed_udp(source, destination, payload), (destination[0], 0))
        self.sent += 1

    def replay(self, recorded: list[Datagram], source: tuple[str, int] | None = None) -> None:
        """Send datagrams a listener recorded (:class:`Capture`) again, to where they went,
        from ``source`` (their own source when None: the sender's address, spoofed)."""
        for datagram in recorded:
            self.send_as(source or datagram.source, datagram.destination, datagram.payload)

    def close(self) -> None:
        if self._raw is not None:
            self._raw.close()
            self._raw = None


@dataclass
class HostileRig:
    """The hosts and daemons of the hostile mesh."""

    fleet: Fleet
    platform: Daemon
    holder: Daemon
    """A station daemon behind a link emulator: it takes control."""
    observer: Daemon
    """A station daemon connected at the same time, not holding control."""
    attacker: Attacker
    capture: Capture
    """Everything the holder's link carried, both ways."""

    @property
    def net(self) -> TestNetwork:
        return self.fleet.net

    @property
    def platform_address(self) -> str:
        return self.platform.host.address

    async def api(self, station: Daemon, method: str, **params: Any) -> Any:
        """``station``'s local API, from its own host (any params: ``port`` included, which
        :func:`netns.rpc` takes for itself); raises :class:`netns.RpcFailed`."""
        body = encode_request(method, params, 1)
        status, payload = await http_post(
            station.host.namespace, "127.0.0.1", API_PORT, "/api/rpc", body
        )
        answer = json.loads(payload) if payload else {}
        if "error" in answer or status != 200:
            raise RpcFailed(status, answer.get("error", {}))
        return answer["result"]

    async def connect_all(self) -> None:
        """Both stations connected to the platform (once it is discovered)."""
        for station in (self.holder, self.observer):
            await self.fleet.wait_listening(station, "127.0.0.1", 8780)
            await self.fleet.connect(station, PLATFORM)

    async def snapshot(self, station: Daemon) -> dict[str, Any]:
        """The platform's latest telemetry as ``station`` receives it (its pushed stream)."""
        report = await self.api(station, "get_telemetry", platform_id=PLATFORM)
        return dict(report.get("snapshot") or {})

    async def section(self, station: Daemon, name: str) -> dict[str, Any]:
        try:
            return dict((await self.snapshot(station)).get(name) or {})
        except RpcFailed:
            return {}

    async def engage(self) -> None:
        """The holder takes control and engages the manual override."""
        await wait_for(lambda: self.fleet.engage(self.holder, PLATFORM), 20, step=0.2)

    async def release(self) -> None:
        for _ in range(3):
            try:
                await self.api(self.holder, "movrd", platform_id=PLATFORM, engaged=False)
                return
            except RpcFailed:
                await asyncio.sleep(0.5)


def hostile_rig_fixture(tag: str) -> Callable[..., Iterator[HostileRig]]:
    """A module-scoped fixture building one :class:`HostileRig` on the module's ``network``
    fixture (:func:`netns.network_fixture`)."""

    @pytest.fixture(scope="module")
    def rig(network: TestNetwork, tmp_path_factory: pytest.TempPathFactory) -> Iterator[HostileRig]:
        fleet = Fleet(network, Path(tmp_path_factory.mktemp(tag)))
        rover_host = network.add_host("rover")
        holder_host = network.add_host("holder", impaired=True)
        observer_host = network.add_host("observer")
        attacker = Attacker(network.add_host("mallory"))
        capture = Capture()
        assert holder_host.relay is not None
        holder_host.relay.taps.append(capture.tap)
        platform = fleet.platform(rover_host, PLATFORM, *PLATFORM_SETTINGS)
        holder = fleet.station(holder_host, "holder", "station.connect_timeout=1.0")
        observer = fleet.station(observer_host, "observer", "station.connect_timeout=1.0")
        try:
            yield HostileRig(fleet, platform, holder, observer, attacker, capture)
        finally:
            attacker.close()
            fleet.stop()
            holder_host.relay.taps.remove(capture.tap)

    return rig


def datagram_counter(host: Host) -> tuple[socket.socket, Callable[[], int]]:
    """A UDP socket bound on ``host`` (a free port) and a function that drains it, returning
    how many datagrams arrived since the last call."""
    sock = socket_in(host.namespace, socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind((host.address, 0))
    sock.setblocking(False)

    def drain() -> int:
        count = 0
        while True:
            try:
                sock.recv(65536)
            except BlockingIOError:
                return count
            count += 1

    return sock, drain


async def count_for(drain: Callable[[], int], seconds: float) -> int:
    """Datagrams arriving over the next ``seconds`` (after what already arrived is dropped)."""
    drain()
    total = 0
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        await asyncio.sleep(0.05)
        total += drain()
    return total + drain()
