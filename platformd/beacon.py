"""Advertisement (R-16): the platform's UDP beacon.

The advertiser keeps the current status word and position from the bus and sends a beacon
(:mod:`brasidas.codecs.beacon`) to every configured destination: at least every
``beacon.max_interval`` seconds, at once when the status word changes or the position moves
``beacon.move_threshold_m`` or more, but never more often than every
``beacon.min_interval`` seconds. The default destination is the loopback broadcast address,
so every station process on this host hears it; a deployment names its mesh's broadcast
address or a multicast group (R-0.6.1; sent with ``IP_MULTICAST_IF`` = ``interface_host`` and
``multicast_ttl``) and ``interface_host`` explicitly.

Each platform also keeps the list of the other platforms online (R-9), with the station's
code (:mod:`brasidas.discovery`): ``list_platforms`` on signaling, ``platforms`` in telemetry.
"""

from __future__ import annotations

import asyncio
import logging
import math
import socket
import time
from typing import Any

from brasidas import discovery, topics
from brasidas.actor import Actor
from brasidas.bus import Topic
from brasidas.codecs import beacon as beacon_codec
from brasidas.codecs.jsonrpc import CallContext
from brasidas.codecs.telemetry_schema import Platforms
from brasidas.config import ConfigError
from brasidas.messages import (
    LightsState,
    OverrideState,
    PatrolStatus,
    PlatformHealth,
    Position,
)
from brasidas.status import Battery, StatusWord
from platformd.boot_counter import boot_counter_path, next_boot
from platformd.context import PlatformContext

_LOGGER = logging.getLogger(__name__)
EARTH_RADIUS_M = 6_371_000.0


def distance_m(a: tuple[float, float], b: tuple[float, float]) -> float:
    """Equirectangular distance: exact enough at the metre scale beacons care about."""
    lat = math.radians((a[0] + b[0]) / 2)
    dx = math.radians(b[1] - a[1]) * math.cos(lat)
    dy = math.radians(b[0] - a[0])
    return EARTH_RADIUS_M * math.hypot(dx, dy)


class BeaconAdvertiser(Actor):
    name = "beacon"

    def __init__(self, ctx: PlatformContext) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self.config = ctx.config.beacon
        self.boot = ctx.boot
        self.seq = 0
        self.sent = 0
        self.send_errors = 0
        self.last_size = 0
        self._wake = asyncio.Event()
        self._sent_word: int | None = None
        self._sent_position: tuple[float, float] | None = None
        self._transport: asyncio.DatagramTransport | None = None

    # ------------------------------------------------------------------ state from the bus

    def current(self) -> beacon_codec.Beacon:
        bus = self.bus
        override: OverrideState | None = bus.last(topics.OVERRIDE_STATE)
        lights: LightsState | None = bus.last(topics.LIGHTS_STATE)
        health: PlatformHealth | None = bus.last(topics.PLATFORM_HEALTH)
        position: Position | None = bus.last(topics.POSITION)
        patrol: PatrolStatus | None = bus.last(topics.PATROL_STATUS)
        status = StatusWord(
            movrd=bool(override and override.engaged),
            main_lights=bool(lights and lights.main),
            positional_lights=bool(lights and lights.positional),
            battery=Battery(health.battery) if health else Battery.UNKNOWN,
            gps_fix=bool(health and health.gps_fix),
            streaming=bool(health and health.streaming),
            session=self.ctx.session_count > 0,
            controller=bool(health and health.controller),
            fault=bool(health and health.fault),
            autonomy=bool(patrol and patrol.state in ("patrolling", "holding")),
        )
        return beacon_codec.Beacon(
            platform_id=self.ctx.config.platform.id,
            signaling_url=self.ctx.signaling_url,
            status=status,
            boot=self.boot,
            seq=self.seq,
            position=(position.latitude, position.longitude) if position else None,
        )

    def _on_change(self, _message: Any) -> None:
        beacon = self.current()
        if beacon.status.encode() != self._sent_word:
            self._wake.set()
        elif beacon.position is not None and (
            self._sent_position is None
            or distance_m(beacon.position, self._sent_position) >= self.config.move_threshold_m
        ):
            self._wake.set()

    # ------------------------------------------------------------------ the loop

    async def run(self) -> None:
        watched: tuple[Topic[Any], ...] = (
            topics.OVERRIDE_STATE,
            topics.LIGHTS_STATE,
            topics.PLATFORM_HEALTH,
            topics.POSITION,
            topics.PATROL_STATUS,
            topics.SESSION_OPENED,
            topics.SESSION_CLOSED,
        )
        for topic in watched:
            self.subscribe(topic, self._on_change)
        loop = asyncio.get_running_loop()
        sock = sender_socket(self.config.interface_host, self.config.multicast_ttl)
        transport, _ = await loop.create_datagram_endpoint(asyncio.DatagramProtocol, sock=sock)
        self._transport = transport
        try:
            while True:
                self.send_now()
                # Never faster than min_interval, whatever changes meanwhile.
                await asyncio.sleep(self.config.min_interval)
                if not self._wake.is_set():
                    remaining = max(0.0, self.config.max_interval - self.config.min_interval)
                    try:
                        async with asyncio.timeout(remaining):
                            await self._wake.wait()
                    except TimeoutError:
                        pass
        finally:
            self._transport = None
            transport.close()

    def send_now(self) -> None:
        assert self._transport is not None
        self._wake.clear()
        self.seq = (self.seq + 1) & 0xFFFFFFFF
        beacon = self.current()
        try:
            datagram = beacon_codec.encode(beacon, self.ctx.fleet_key)
        except ValueError as err:  # an over-long id or URL: a configuration error
            _LOGGER.error("beacon not sent: %s", err)
            self.send_errors += 1
            return
        self.last_size = len(datagram)
        for host in self.config.destinations:
            try:
                self._transport.sendto(datagram, (host, self.config.port))
                self.sent += 1
            except OSError as err:  # unreachable network: count, keep advertising
                self.send_errors += 1
                _LOGGER.debug("beacon to %s failed: %s", host, err)
        self._sent_word = beacon.status.encode()
        self._sent_position = beacon.position

    def stats(self) -> dict[str, Any]:
        return {
            "sent": self.sent,
            "send_errors": self.send_errors,
            "size": self.last_size,
            "destinations": list(self.config.destinations),
        }


def sender_socket(interface_host: str, multicast_ttl: int) -> socket.socket:
    """A UDP socket for beacons to broadcast, multicast and unicast destinations."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_BROADCAST, 1)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, multicast_ttl)
        sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
        if interface_host not in ("", "0.0.0.0"):
            # Multicast leaves by this interface, not by the routing table's choice.
            sock.setsockopt(
                socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(interface_host)
            )
        sock.setblocking(False)
        sock.bind((interface_host, 0))
    except OSError:
        sock.close()
        raise
    return sock


def listen_settings(ctx: PlatformContext) -> discovery.ListenSettings:
    """Hear the others where this platform's own beacons go (same port, same groups)."""
    config = ctx.config.beacon
    interface = config.interface_host
    return discovery.ListenSettings(
        port=config.port,
        host=config.listen_host,
        groups=tuple(d for d in config.destinations if discovery.is_multicast(d)),
        interfaces=() if interface in ("", "0.0.0.0") else (interface,),
        expiry=config.expiry,
    )


def flat_counters(stats: dict[str, Any]) -> dict[str, int]:
    """``{"dropped": {"forged": 1}}`` as ``{"dropped_forged": 1}`` (diagnostics are flat)."""
    flat: dict[str, int] = {}
    for name, value in stats.items():
        if isinstance(value, dict):
            flat.update({f"{name}_{key}": count for key, count in value.items()})
        elif isinstance(value, int):
            flat[name] = value
    return flat


def setup_directory(ctx: PlatformContext) -> discovery.PlatformDirectory:
    """R-9: the other platforms online, served by ``list_platforms`` and in telemetry."""
    directory = discovery.PlatformDirectory(
        ctx.fleet_key, ctx.config.beacon.expiry, self_id=ctx.config.platform.id
    )
    settings = listen_settings(ctx)
    ctx.supervisor.start(discovery.BeaconListener(ctx.bus, directory, settings))

    async def list_platforms(call: CallContext) -> list[dict[str, Any]]:
        """The other platforms online (heard within ``beacon.expiry`` seconds)."""
        return directory.entries()

    ctx.rpc.add("list_platforms", list_platforms)
    ctx.telemetry.register(
        Platforms,
        lambda: Platforms({entry["id"]: round(entry["age_s"], 1) for entry in directory.entries()}),
    )
    ctx.telemetry.add_counters("discovery", lambda: flat_counters(directory.stats()))
    return directory


def check_beacon_fits(platform_id: str, signaling_url: str, key: bytes | None) -> None:
    """Refuse to start (ConfigError) when the largest beacon this platform can send, with its id
    and signaling URL, would not fit: it would start, then fail every beacon."""
    largest = beacon_codec.Beacon(
        platform_id,
        signaling_url,
        StatusWord.decode(0xFFFFFFFF),
        0xFFFFFFFF,
        0xFFFFFFFF,
        (-89.9999999, -179.9999999),
    )
    try:
        beacon_codec.encode(largest, key if key is not None else bytes(32))
    except ValueError as err:
        raise ConfigError("platform.id", f"with signaling URL {signaling_url}: {err}") from None


async def async_setup(ctx: PlatformContext) -> None:
    if not ctx.config.beacon.enabled:
        return
    if not ctx.signaling_url:
        raise RuntimeError(
            "the beacon advertises signaling's URL: set up platformd.signaling first"
        )
    check_beacon_fits(ctx.config.platform.id, ctx.signaling_url, ctx.fleet_key)
    ctx.boot = await asyncio.to_thread(next_boot, boot_counter_path(), time.time())
    if ctx.config.beacon.listen:
        setup_directory(ctx)
    advertiser = BeaconAdvertiser(ctx)
    ctx.supervisor.start(advertiser)
    ctx.capabilities.register(
        "beacon",
        lambda: {
            "port": ctx.config.beacon.port,
            "max_interval": ctx.config.beacon.max_interval,
        },
    )
