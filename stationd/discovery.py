"""Discovery (R-9): the station's list of platforms online, from their beacons.

:class:`PlatformDirectory` is the sans-IO part: it authenticates beacons, refuses replays,
stamps each entry with the station's own clock and drops an entry ``discovery.expiry``
seconds after its last beacon. :class:`BeaconListener` moves datagrams into it and publishes
:data:`~brasidas.topics.PLATFORM_DISCOVERED` / :data:`~brasidas.topics.PLATFORM_LOST`.
The daemon serves the list as the ``list_platforms`` API method; ``brasidas-station list``
uses :func:`discover` on its own socket (the port is shared with ``SO_REUSEPORT``; beacons go
to a broadcast address, so every listener on the host hears them).
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from brasidas import topics
from brasidas.actor import Actor
from brasidas.codecs import beacon as beacon_codec
from brasidas.codecs.beacon import Beacon, BeaconError, DropReason, ReplayGuard
from brasidas.codecs.jsonrpc import CallContext
from brasidas.config import StationConfig
from brasidas.messages import PlatformSighting
from stationd.context import StationContext

_LOGGER = logging.getLogger(__name__)


@dataclass
class DiscoveredPlatform:
    beacon: Beacon
    address: str
    """Where the last beacon came from."""
    first_seen: float
    last_seen: float
    """Station monotonic clock at reception."""
    last_seen_wall: float
    beacons: int = 1

    def as_dict(self, now: float) -> dict[str, Any]:
        status = dataclasses.asdict(self.beacon.status)
        status["battery"] = self.beacon.status.battery.name.lower()
        return {
            "id": self.beacon.platform_id,
            "url": self.beacon.signaling_url,
            "address": self.address,
            "status": status,
            "status_word": self.beacon.status.encode(),
            "position": list(self.beacon.position) if self.beacon.position else None,
            "age_s": round(now - self.last_seen, 3),
            "last_seen": self.last_seen_wall,
            "beacons": self.beacons,
        }


class PlatformDirectory:
    """The platforms heard lately. Feed it datagrams; ask it for the live entries."""

    def __init__(
        self,
        key: bytes | None,
        expiry: float,
        *,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        self.key = key
        self.expiry = expiry
        self._clock = clock
        self._wall_clock = wall_clock
        self.platforms: dict[str, DiscoveredPlatform] = {}
        self._replay = ReplayGuard()
        self.received = 0
        self.accepted = 0
        self.dropped: dict[str, int] = {reason.value: 0 for reason in DropReason}

    def receive(self, datagram: bytes, address: str) -> tuple[DiscoveredPlatform, bool] | None:
        """Handle one datagram; returns (entry, is_new) or None when it was dropped."""
        self.received += 1
        try:
            beacon = beacon_codec.decode(datagram, self.key)
            self._replay.check(beacon)
        except BeaconError as err:
            self.dropped[err.reason.value] += 1
            _LOGGER.debug("beacon from %s dropped: %s", address, err)
            return None
        self.accepted += 1
        now = self._clock()
        entry = self.platforms.get(beacon.platform_id)
        if entry is None:
            entry = DiscoveredPlatform(beacon, address, now, now, self._wall_clock())
            self.platforms[beacon.platform_id] = entry
            return entry, True
        entry.beacon = beacon
        entry.address = address
        entry.last_seen = now
        entry.last_seen_wall = self._wall_clock()
        entry.beacons += 1
        return entry, False

    def expire(self) -> list[DiscoveredPlatform]:
        """Drop and return the entries silent for longer than the expiry."""
        now = self._clock()
        gone = [e for e in self.platforms.values() if now - e.last_seen > self.expiry]
        for entry in gone:
            del self.platforms[entry.beacon.platform_id]
        return gone

    def entries(self) -> list[dict[str, Any]]:
        self.expire()
        now = self._clock()
        return [self.platforms[name].as_dict(now) for name in sorted(self.platforms)]

    def stats(self) -> dict[str, Any]:
        return {
            "received": self.received,
            "accepted": self.accepted,
            "dropped": dict(self.dropped),
            "platforms": len(self.platforms),
        }


def listen_socket(host: str, port: int) -> socket.socket:
    """A UDP socket for beacons that other listeners on this host may share."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        sock.setblocking(False)
        sock.bind((host, port))
    except OSError:
        sock.close()
        raise
    return sock


class _BeaconProtocol(asyncio.DatagramProtocol):
    def __init__(self, on_datagram: Callable[[bytes, str], object]) -> None:
        self.on_datagram = on_datagram

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        self.on_datagram(data, str(addr[0]))


class BeaconListener(Actor):
    name = "discovery"

    def __init__(self, ctx: StationContext, directory: PlatformDirectory) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self.directory = directory

    async def run(self) -> None:
        config = self.ctx.config.discovery
        loop = asyncio.get_running_loop()
        sock = listen_socket(config.bind_host, config.port)
        transport, _ = await loop.create_datagram_endpoint(
            lambda: _BeaconProtocol(self._on_datagram), sock=sock
        )
        try:
            while True:
                await asyncio.sleep(min(0.5, config.expiry / 4))
                for entry in self.directory.expire():
                    _LOGGER.info("platform %s lost (no beacon)", entry.beacon.platform_id)
                    self.bus.publish(topics.PLATFORM_LOST, _sighting(entry))
        finally:
            transport.close()

    def _on_datagram(self, data: bytes, address: str) -> None:
        result = self.directory.receive(data, address)
        if result is None:
            return
        entry, is_new = result
        if is_new:
            _LOGGER.info(
                "platform %s discovered at %s", entry.beacon.platform_id, entry.beacon.signaling_url
            )
            self.bus.publish(topics.PLATFORM_DISCOVERED, _sighting(entry))


def _sighting(entry: DiscoveredPlatform) -> PlatformSighting:
    return PlatformSighting(entry.beacon.platform_id, entry.beacon.signaling_url, entry.address)


async def discover(config: StationConfig, key: bytes | None, wait: float) -> list[dict[str, Any]]:
    """Listen for ``wait`` seconds on the discovery port; the platforms heard, as dicts."""
    directory = PlatformDirectory(key, config.discovery.expiry)
    loop = asyncio.get_running_loop()
    sock = listen_socket(config.discovery.bind_host, config.discovery.port)
    transport, _ = await loop.create_datagram_endpoint(
        lambda: _BeaconProtocol(lambda data, address: directory.receive(data, address)),
        sock=sock,
    )
    try:
        await asyncio.sleep(wait)
    finally:
        transport.close()
    return directory.entries()


async def async_setup(ctx: StationContext) -> None:
    directory = PlatformDirectory(ctx.fleet_key, ctx.config.discovery.expiry)
    ctx.supervisor.start(BeaconListener(ctx, directory))

    async def list_platforms(call: CallContext) -> list[dict[str, Any]]:
        """The platforms online (heard within ``discovery.expiry`` seconds)."""
        return directory.entries()

    async def discovery_stats(call: CallContext) -> dict[str, Any]:
        """Beacons received, accepted and dropped by reason."""
        return directory.stats()

    ctx.api.add("list_platforms", list_platforms, session_required=False)
    ctx.api.add("discovery_stats", discovery_stats, session_required=False)
