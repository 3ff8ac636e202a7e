"""Many discovery-only platforms in one process: real, signed beacons from one address each.

A :class:`BeaconFleet` stands in for a fleet when only discovery is under test (a station's
list with 20 platforms, the mesh's beacon load): each member sends the beacon a platform
sends (:mod:`brasidas.codecs.beacon`, with the fleet key), from its own source address,
every ``interval`` seconds, on a thread of its own. :meth:`BeaconFleet.silence` stops one,
as if it had died.
"""

from __future__ import annotations

import secrets
import socket
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from brasidas.codecs import beacon as beacon_codec
from brasidas.status import Battery, StatusWord


@dataclass
class _Member:
    platform_id: str
    address: str
    sock: socket.socket
    boot: int
    seq: int = 0
    silenced_at: float | None = None
    last_sent: float | None = None


class BeaconFleet:
    """``ids[i]`` beacons from ``addresses[i]`` to ``destination``:``port``."""

    def __init__(
        self,
        ids: Sequence[str],
        addresses: Sequence[str],
        key: bytes | None,
        destination: str,
        port: int,
        *,
        interval: float = 3.0,
        socket_factory: Callable[[], socket.socket] | None = None,
    ) -> None:
        if len(ids) != len(addresses):
            raise ValueError("one address per platform")
        self.key = key
        self.destination = (destination, port)
        self.interval = interval
        self.sent = 0
        self.bytes_sent = 0
        self.members: dict[str, _Member] = {}
        factory = socket_factory or (lambda: socket.socket(socket.AF_INET, socket.SOCK_DGRAM))
        for platform_id, address in zip(ids, addresses, strict=True):
            sock = factory()
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
            sock.bind((address, 0))
            self.members[platform_id] = _Member(platform_id, address, sock, secrets.randbits(32))
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="beacon-fleet", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def silence(self, platform_id: str) -> float:
        """Stop ``platform_id``'s beacons; returns when its last one was sent."""
        member = self.members[platform_id]
        member.silenced_at = time.monotonic()
        return member.last_sent or member.silenced_at

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(5)
        for member in self.members.values():
            member.sock.close()

    def _beacon(self, member: _Member) -> bytes:
        member.seq += 1
        status = StatusWord(battery=Battery.HIGH, controller=True, gps_fix=True)
        beacon = beacon_codec.Beacon(
            member.platform_id,
            f"http://{member.address}:8765",
            status,
            member.boot,
            member.seq,
            (37.9415, 23.6530),
        )
        return beacon_codec.encode(beacon, self.key)

    def _run(self) -> None:
        members = list(self.members.values())
        # Spread the members over the interval, as independent platforms would be.
        step = self.interval / max(1, len(members))
        while not self._stop.is_set():
            for member in members:
                if self._stop.wait(step):
                    return
                if member.silenced_at is not None:
                    continue
                datagram = self._beacon(member)
                try:
                    member.sock.sendto(datagram, self.destination)
                except OSError:
                    continue
                member.last_sent = time.monotonic()
                self.sent += 1
                self.bytes_sent += len(datagram)
