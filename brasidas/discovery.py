"""Discovery (R-9): a list of the platforms online, from their beacons; stations and platforms.

:class:`PlatformDirectory` is the sans-IO part: it authenticates beacons, refuses replays,
stamps each entry with the listener's own clock and drops an entry ``expiry`` seconds after
its last beacon. :class:`BeaconListener` moves datagrams into it and publishes
:data:`~brasidas.topics.PLATFORM_DISCOVERED` / :data:`~brasidas.topics.PLATFORM_LOST`.
A station (``stationd.discovery``) and every platform (``platformd.beacon``) run one each.

Beacons arrive by broadcast, by multicast (R-0.6.1) or unicast. :func:`listen_socket` shares
the port with the host's other listeners (``SO_REUSEPORT``) and joins the multicast groups
it is given (IGMP) on each interface named, or on every interface of the host.
"""

from __future__ import annotations

import asyncio
import dataclasses
import ipaddress
import logging
import socket
import struct
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

from brasidas import topics
from brasidas.actor import Actor
from brasidas.bus import Bus
from brasidas.codecs import beacon as beacon_codec
from brasidas.codecs.beacon import Beacon, BeaconError, DropReason, ReplayGuard
from brasidas.messages import PlatformSighting

_LOGGER = logging.getLogger(__name__)

IP_MULTICAST_ALL = 49
"""Linux <netinet/in.h>; not in Python's socket module before 3.12."""
EXPIRY = 4.0
"""R-9.3: a platform is dropped this long after its last beacon (the config's default)."""


@dataclass(frozen=True)
class ListenSettings:
    """Where a listener hears beacons."""

    port: int
    host: str = "0.0.0.0"
    groups: tuple[str, ...] = ()
    """Multicast groups to join."""
    interfaces: tuple[str, ...] = ()
    """Local addresses of the interfaces to join the groups on; empty: every interface."""
    expiry: float = EXPIRY


@dataclass
class DiscoveredPlatform:
    beacon: Beacon
    address: str
    """Where the last beacon came from."""
    first_seen: float
    last_seen: float
    """The listener's monotonic clock at reception."""
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
    """The platforms heard lately. Feed it datagrams; ask it for the live entries.

    ``self_id`` is the listening platform's own id: its own beacons (heard back through
    broadcast or multicast loop) are counted under ``own`` and not listed.
    """

    def __init__(
        self,
        key: bytes | None,
        expiry: float = EXPIRY,
        *,
        self_id: str | None = None,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        self.key = key
        self.expiry = expiry
        self.self_id = self_id
        self._clock = clock
        self._wall_clock = wall_clock
        self.platforms: dict[str, DiscoveredPlatform] = {}
        self._replay = ReplayGuard()
        self.received = 0
        self.accepted = 0
        self.own = 0
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
        if beacon.platform_id == self.self_id:
            self.own += 1
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

    def announce_boot(self, platform_id: str, boot: int) -> None:
        """A connected platform's authenticated boot number (:meth:`ReplayGuard.announce`)."""
        self._replay.announce(platform_id, boot)

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
            "own": self.own,
            "dropped": dict(self.dropped),
            "platforms": len(self.platforms),
        }


def is_multicast(address: str) -> bool:
    try:
        return ipaddress.ip_address(address).is_multicast
    except ValueError:
        return False


def listen_socket(
    host: str, port: int, groups: Sequence[str] = (), interfaces: Sequence[str] = ()
) -> socket.socket:
    """A UDP socket for beacons that other listeners on this host may share.

    It joins each multicast group in ``groups`` on the interfaces whose local addresses are
    ``interfaces``, or on every interface when none is named (those that refuse, e.g. down
    or without multicast, are skipped; if none accepts, OSError names the group).
    """
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEPORT, 1)
        sock.setblocking(False)
        # Only the groups this socket joined, not every group some socket of the host did.
        sock.setsockopt(socket.IPPROTO_IP, IP_MULTICAST_ALL, 0)
        sock.bind((host, port))
        for group in groups:
            _join(sock, group, interfaces)
    except OSError:
        sock.close()
        raise
    return sock


def _join(sock: socket.socket, group: str, interfaces: Sequence[str]) -> None:
    """IGMP-join ``group`` per interface (by address, or every interface by index)."""
    if not is_multicast(group):
        raise OSError(f"{group} is not a multicast address")
    target = socket.inet_aton(group)
    requests: list[tuple[str, bytes]] = []
    if interfaces:
        requests = [(a, target + socket.inet_aton(a)) for a in interfaces]
    else:
        # struct ip_mreqn: group, local address (any), interface index.
        zero = socket.inet_aton("0.0.0.0")
        requests = [
            (name, target + zero + struct.pack("@i", index))
            for index, name in socket.if_nameindex()
        ]
    joined = []
    for name, request in requests:
        try:
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, request)
        except OSError as err:
            _LOGGER.debug("cannot join %s on %s: %s", group, name, err)
            continue
        joined.append(name)
    if not joined:
        raise OSError(f"cannot join multicast group {group} on any interface")
    _LOGGER.info("listening for beacons on multicast %s via %s", group, ", ".join(joined))


class _BeaconProtocol(asyncio.DatagramProtocol):
    def __init__(self, on_datagram: Callable[[bytes, str], object]) -> None:
        self.on_datagram = on_datagram

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        self.on_datagram(data, str(addr[0]))


class BeaconListener(Actor):
    """Keeps ``directory`` fed and expired; announces platforms discovered and lost."""

    name = "discovery"

    def __init__(self, bus: Bus, directory: PlatformDirectory, settings: ListenSettings) -> None:
        super().__init__(bus)
        self.directory = directory
        self.settings = settings

    async def run(self) -> None:
        settings = self.settings
        loop = asyncio.get_running_loop()
        sock = listen_socket(settings.host, settings.port, settings.groups, settings.interfaces)
        transport, _ = await loop.create_datagram_endpoint(
            lambda: _BeaconProtocol(self._on_datagram), sock=sock
        )
        try:
            while True:
                await asyncio.sleep(min(0.5, self.directory.expiry / 4))
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


async def discover(
    settings: ListenSettings, key: bytes | None, wait: float
) -> list[dict[str, Any]]:
    """Listen for ``wait`` seconds; the platforms heard, as dicts."""
    directory = PlatformDirectory(key, settings.expiry)
    loop = asyncio.get_running_loop()
    sock = listen_socket(settings.host, settings.port, settings.groups, settings.interfaces)
    transport, _ = await loop.create_datagram_endpoint(
        lambda: _BeaconProtocol(lambda data, address: directory.receive(data, address)),
        sock=sock,
    )
    try:
        await asyncio.sleep(wait)
    finally:
        transport.close()
    return directory.entries()
