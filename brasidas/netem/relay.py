"""The link emulator's transport: a userspace bridge port between two interfaces.

A :class:`FrameRelay` reads every Ethernet frame arriving on one interface with a packet
socket and writes it out of the other, through one :class:`~brasidas.netem.core.Impairment`
per direction. Being a layer-2 port, it carries everything a real radio link would (ARP,
broadcast and multicast beacons, IGMP, TCP signaling, UDP velocity, telemetry and video),
without the daemons knowing it is there. The sockets use ``PACKET_VNET_HDR``, so frames whose
checksum or segmentation the kernel left to the "hardware" (veth offloads) are passed on with
that work still flagged, and the sending side's kernel finishes it: no ethtool needed. A
segmented TCP burst then travels (and is lost) as one frame; the UDP the daemons send is not
segmented. The relay runs on a thread of its own so that it keeps forwarding whatever the
caller's event loop is doing; its methods may be called from any thread.
"""

from __future__ import annotations

import contextlib
import os
import select
import socket
import struct
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

from brasidas.netem.core import CLEAN, Impairment, Profile

ETH_P_ALL = 0x0003
SOL_PACKET = 263
PACKET_VNET_HDR = 15
SO_RCVBUFFORCE = 33
PACKET_STATISTICS = 6
RECEIVE_BUFFER = 8 * 1024 * 1024
"""Frames queue here while the relay's thread waits for a CPU; a full buffer drops them."""
RELAY_NICE = -10
"""The relay thread's nice value (the daemons and the tests run at 0)."""
VNET_HEADER = 10
"""struct virtio_net_hdr in front of every frame read or written with PACKET_VNET_HDR."""
MAX_FRAME = 65536 + VNET_HEADER

DOWN = "down"
"""Bridge (the rest of the network) to the host."""
UP = "up"
"""Host to the bridge."""

Tap = Callable[[str, bytes, float], None]
"""Called on the relay's thread with (direction, Ethernet frame, time) for each frame delivered."""


class FrameRelay:
    """Bridges ``host_side`` and ``bridge_side`` (interfaces of the calling thread's namespace)."""

    def __init__(
        self,
        host_side: str,
        bridge_side: str,
        *,
        seed: int = 0,
        name: str = "",
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.name = name or host_side
        self._clock = clock
        self.links = {DOWN: Impairment(seed=seed * 2), UP: Impairment(seed=seed * 2 + 1)}
        self.taps: list[Tap] = []
        self.arrival_taps: list[Tap] = []
        """Called with each frame as the relay reads it, before the impairments."""
        self.send_errors = 0
        self.socket_drops = 0
        """Frames the kernel dropped because the relay did not read them in time (counted)."""
        self._lock = threading.Lock()
        self._host = _packet_socket(host_side)
        try:
            self._bridge = _packet_socket(bridge_side)
        except OSError:
            self._host.close()
            raise
        self._wake_r, self._wake_w = os.pipe()
        self._stopping = False
        self._thread: threading.Thread | None = None

    # ------------------------------------------------------------------ control

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name=f"netem:{self.name}", daemon=True)
        self._thread.start()

    def set_profiles(self, *, down: Profile | None = None, up: Profile | None = None) -> None:
        with self._lock:
            if down is not None:
                self.links[DOWN].set_profile(down)
            if up is not None:
                self.links[UP].set_profile(up)
        self._wake()

    def clear(self) -> None:
        """A clean link both ways (not cut)."""
        self.set_profiles(down=CLEAN, up=CLEAN)
        self.restore()

    def cut(self) -> float:
        """Cut both directions; returns the time of the cut (relay clock)."""
        with self._lock:
            for link in self.links.values():
                link.cut()
            return self._clock()

    def restore(self) -> None:
        with self._lock:
            for link in self.links.values():
                link.restore()
        self._wake()

    def stats(self) -> dict[str, Any]:
        with self._lock:
            return {
                direction: {
                    "profile": link.profile.describe(),
                    "state": "cut" if link.is_cut else "up",
                    **asdict(link.counters),
                }
                for direction, link in self.links.items()
            } | {
                "send_errors": self.send_errors,
                "socket_drops": self._socket_drops(),
            }

    def _socket_drops(self) -> int:
        """Add what the kernel dropped since the last call (reading resets its counters)."""
        for sock in (self._host, self._bridge):
            with contextlib.suppress(OSError):
                _, drops = struct.unpack("II", sock.getsockopt(SOL_PACKET, PACKET_STATISTICS, 8))
                self.socket_drops += drops
        return self.socket_drops

    def close(self) -> None:
        """Stop the thread and close the sockets (idempotent)."""
        if self._stopping:
            return
        self._stopping = True
        self._wake()
        if self._thread is not None:
            self._thread.join(5)
        for sock in (self._host, self._bridge):
            sock.close()
        os.close(self._wake_r)
        os.close(self._wake_w)

    # ------------------------------------------------------------------ the thread

    def _wake(self) -> None:
        with contextlib.suppress(OSError):
            os.write(self._wake_w, b"x")

    def _run(self) -> None:
        # A link does not wait for a CPU: on a loaded machine this thread, starved, held
        # frames for tens of ms, which the video's congestion control rightly read as a queue
        # over capacity. Ahead of the daemons (root only; otherwise as it was).
        with contextlib.suppress(OSError):
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), RELAY_NICE)
        source = {id(self._bridge): DOWN, id(self._host): UP}
        target = {DOWN: self._host, UP: self._bridge}
        while not self._stopping:
            with self._lock:
                deadlines = [
                    d for link in self.links.values() if (d := link.deadline()) is not None
                ]
            timeout = max(0.0, min(deadlines) - self._clock()) if deadlines else None
            waitable = [self._host.fileno(), self._bridge.fileno(), self._wake_r]
            readable, _, _ = select.select(waitable, [], [], timeout)
            now = self._clock()
            for fd in readable:
                if fd == self._wake_r:
                    os.read(self._wake_r, 4096)
                    continue
                ready = self._host if fd == self._host.fileno() else self._bridge
                # Drain what is queued: under load several frames arrive per wake-up.
                while True:
                    try:
                        frame, address = ready.recvfrom(MAX_FRAME, socket.MSG_DONTWAIT)
                    except (BlockingIOError, InterruptedError):
                        break
                    except OSError:
                        break  # closing
                    if address[2] == socket.PACKET_OUTGOING:
                        continue  # our own transmission, seen by the tap
                    direction = source[id(ready)]
                    for tap in self.arrival_taps:
                        tap(direction, frame[VNET_HEADER:], now)
                    with self._lock:
                        self.links[direction].feed(frame, now)
            for direction, link in self.links.items():
                with self._lock:
                    frames = link.due(now)
                for frame in frames:
                    try:
                        target[direction].send(frame)
                    except OSError:
                        self.send_errors += 1
                        continue
                    for tap in self.taps:
                        tap(direction, frame[VNET_HEADER:], now)


def _packet_socket(interface: str) -> socket.socket:
    sock = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(ETH_P_ALL))
    try:
        try:  # root may exceed net.core.rmem_max
            sock.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, RECEIVE_BUFFER)
        except PermissionError:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECEIVE_BUFFER)
        sock.setsockopt(SOL_PACKET, PACKET_VNET_HDR, 1)
        sock.bind((interface, 0))
    except OSError:
        sock.close()
        raise
    return sock


# ---------------------------------------------------------------------- reading frames


@dataclass(frozen=True)
class Datagram:
    """A UDP datagram or a TCP segment's payload seen on the link."""

    protocol: str
    """"udp" or "tcp"."""
    source: tuple[str, int]
    destination: tuple[str, int]
    payload: bytes


def parse(frame: bytes) -> Datagram | None:
    """The IPv4 UDP/TCP content of an Ethernet frame, or None for anything else."""
    if len(frame) < 34 or frame[12:14] != b"\x08\x00":
        return None
    ip = frame[14:]
    header = (ip[0] & 0x0F) * 4
    total = struct.unpack("!H", ip[2:4])[0]
    protocol = ip[9]
    src, dst = socket.inet_ntoa(ip[12:16]), socket.inet_ntoa(ip[16:20])
    body = ip[header:total]
    if protocol == 17 and len(body) >= 8:
        sport, dport = struct.unpack("!HH", body[:4])
        return Datagram("udp", (src, sport), (dst, dport), body[8:])
    if protocol == 6 and len(body) >= 20:
        sport, dport = struct.unpack("!HH", body[:4])
        offset = (body[12] >> 4) * 4
        return Datagram("tcp", (src, sport), (dst, dport), body[offset:])
    return None
