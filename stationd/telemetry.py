"""The station's telemetry receiver and annunciator (the seed's Status Display, ch. 11 §4.2).

For every connected platform a :class:`TelemetryLink` binds a UDP socket, asks the platform to
``request_telemetry`` to it, verifies each datagram with the session key, merges the sections
into the latest snapshot and keeps link statistics. The :class:`Annunciator` turns snapshots
and link figures into named warnings (low battery, controller over-temperature, GPS fix lost,
link degraded, failed streams); raising and clearing each one publishes a group 90
:class:`~brasidas.messages.StationNotification` on the station bus.

Local API: ``get_telemetry(platform_id)`` (snapshot, link, warnings) and
``telemetry_notifications(limit)`` (the most recent notifications).
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import ipaddress
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from brasidas import topics
from brasidas.actor import Actor, wait_forever
from brasidas.codecs.commands import CommandCode
from brasidas.codecs.jsonrpc import UNAVAILABLE, CallContext, RpcError
from brasidas.codecs.telemetry import TelemetryDecoder
from brasidas.config import TelemetryReceiverSection
from brasidas.messages import StationNotification
from stationd.context import StationContext

_LOGGER = logging.getLogger(__name__)

NOTIFICATION_GROUP = 90
"""Station-only notifications (seed ch. 11 §1)."""
LOW_BATTERY = CommandCode(NOTIFICATION_GROUP, 10)
CONTROLLER_OVER_TEMPERATURE = CommandCode(NOTIFICATION_GROUP, 11)
GPS_FIX_LOST = CommandCode(NOTIFICATION_GROUP, 12)
LINK_DEGRADED = CommandCode(NOTIFICATION_GROUP, 13)
STREAM_FAILED = CommandCode(NOTIFICATION_GROUP, 14)
TICK = 0.1
"""How often silence is checked when no datagram arrives."""
NOTIFICATIONS_KEPT = 100
REQUEST_AGAIN_FACTOR = 3.0
"""After this many ``silence_s`` without data the station asks for its stream again."""
FAILED_STREAM_STATES = frozenset({"failed", "error"})


# --------------------------------------------------------------------------- link statistics


class LinkStats:
    """Loss over the last ``window`` sequence numbers, and silence since the last datagram."""

    def __init__(self, window: int) -> None:
        self.window = max(1, window)
        self.received = 0
        self.first_seq: int | None = None
        self.last_seq: int | None = None
        self.last_at: float | None = None
        self.started_at: float | None = None
        self._recent: collections.deque[int] = collections.deque()

    def start(self, now: float) -> None:
        """The stream was requested at ``now``: silence counts from here until data arrives."""
        self.started_at = now

    def accepted(self, seq: int, now: float) -> None:
        if self.first_seq is None or (
            self.last_seq is not None and seq - self.last_seq > self.window
        ):
            # First datagram, or the platform restarted its stream further on: start over.
            self.first_seq = seq
            self._recent.clear()
        self.received += 1
        self.last_seq = seq
        self.last_at = now
        self._recent.append(seq)
        while self._recent and self._recent[0] <= seq - self.window:
            self._recent.popleft()

    @property
    def loss_pct(self) -> float:
        """Share of the expected sequence numbers in the window that never arrived."""
        if self.last_seq is None or self.first_seq is None:
            return 0.0
        expected = min(self.window, self.last_seq - self.first_seq + 1)
        return round(100.0 * max(0, expected - len(self._recent)) / expected, 1)

    def silence(self, now: float) -> float | None:
        """Seconds without a valid datagram (since the request when none came yet)."""
        since = self.last_at if self.last_at is not None else self.started_at
        return None if since is None else max(0.0, now - since)


# --------------------------------------------------------------------------- annunciator


@dataclass(frozen=True)
class Alert:
    """One annunciator warning, active since ``since`` (station clock)."""

    name: str
    code: CommandCode
    message: str
    since: float

    def as_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "code": str(self.code),
            "message": self.message,
            "since": self.since,
        }


@dataclass(frozen=True)
class Change:
    """A warning raised (``active``) or cleared."""

    warning: Alert
    active: bool


class Annunciator:
    """Pure: feed snapshots and link figures with the time; get warnings raised and cleared."""

    def __init__(self, config: TelemetryReceiverSection) -> None:
        self.config = config
        self.active: dict[str, Alert] = {}

    def evaluate(
        self, snapshot: dict[str, Any], loss_pct: float, silence: float | None, now: float
    ) -> list[Change]:
        """Update the warnings from the latest values; returns what changed."""
        wanted: dict[str, tuple[CommandCode, str]] = {}
        keep: set[str] = set()
        self._battery(snapshot.get("battery"), wanted, keep)
        self._temperature(snapshot.get("controller"), wanted, keep)
        gps = snapshot.get("gps")
        if isinstance(gps, dict) and gps.get("fix") is False:
            lost = gps.get("lost_for_s")
            wanted["gps_fix_lost"] = (
                GPS_FIX_LOST,
                f"GPS fix lost ({lost:.0f} s ago)"
                if isinstance(lost, int | float)
                else "no GPS fix yet",  # the receiver has not had one since it started
            )
        link: list[str] = []
        if silence is not None and silence >= self.config.silence_s:
            link.append(f"telemetry silent for {silence:.1f} s")
        if loss_pct > self.config.loss_warn_pct:
            link.append(f"{loss_pct:.0f}% of telemetry lost")
        if link:
            wanted["link_degraded"] = (LINK_DEGRADED, "link degraded: " + ", ".join(link))
        streams = snapshot.get("streams")
        if isinstance(streams, dict):
            for name, state in streams.items():
                if isinstance(state, str) and state.lower() in FAILED_STREAM_STATES:
                    wanted[f"stream_failed:{name}"] = (STREAM_FAILED, f"stream {name} failed")
        changes: list[Change] = []
        for name in list(self.active):
            if name not in wanted and name not in keep:
                changes.append(Change(self.active.pop(name), False))
        for name, (code, message) in wanted.items():
            current = self.active.get(name)
            if current is None:
                self.active[name] = Alert(name, code, message, now)
                changes.append(Change(self.active[name], True))
            elif current.message != message:
                # Same warning, fresher wording (the figure changed): no new notification.
                self.active[name] = Alert(name, code, message, current.since)
        return changes

    def _battery(self, battery: Any, wanted: dict[str, Any], keep: set[str]) -> None:
        if not isinstance(battery, dict):
            return
        volts = battery.get("volts")
        volts = volts if isinstance(volts, int | float) and not isinstance(volts, bool) else None
        low_level = battery.get("level") == "low"
        config = self.config
        if low_level or (volts is not None and volts < config.battery_low_v):
            figure = f" ({volts:.1f} V)" if volts is not None else ""
            wanted["low_battery"] = (LOW_BATTERY, f"low battery{figure}")
        elif "low_battery" in self.active and volts is not None and volts < config.battery_clear_v:
            keep.add("low_battery")  # hysteresis: not yet recovered

    def _temperature(self, controller: Any, wanted: dict[str, Any], keep: set[str]) -> None:
        if not isinstance(controller, dict):
            return
        temps = controller.get("temps_c")
        values = temps if isinstance(temps, list) else [temps]
        readings = [t for t in values if isinstance(t, int | float) and not isinstance(t, bool)]
        if not readings:
            return
        hottest = max(readings)
        if hottest >= self.config.controller_max_c:
            wanted["controller_over_temperature"] = (
                CONTROLLER_OVER_TEMPERATURE,
                f"controller over temperature ({hottest:.0f} °C)",
            )
        elif "controller_over_temperature" in self.active and hottest >= (
            self.config.controller_clear_c
        ):
            keep.add("controller_over_temperature")

    def clear_all(self) -> list[Change]:
        changes = [Change(warning, False) for warning in self.active.values()]
        self.active.clear()
        return changes


# --------------------------------------------------------------------------- one platform


class TelemetryLink(asyncio.DatagramProtocol):
    """Receives and verifies one platform's telemetry; keeps its snapshot and warnings."""

    def __init__(
        self,
        platform_id: str,
        session_key: bytes | None,
        config: TelemetryReceiverSection,
        publish: Callable[[StationNotification], None],
        *,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], float] = time.time,
    ) -> None:
        self.platform_id = platform_id
        self.decoder = TelemetryDecoder(platform_id, session_key)
        self.config = config
        self.stats = LinkStats(config.loss_window)
        self.annunciator = Annunciator(config)
        self.snapshot: dict[str, Any] = {}
        self.platform_time: float | None = None
        self.bytes_received = 0
        self.max_datagram = 0
        self.error = ""
        """Why there is no stream (the platform refused request_telemetry), if so."""
        self.round_trip_ms: float | None = None
        self._publish = publish
        self._clock = clock
        self._wall_clock = wall_clock
        self.transport: asyncio.DatagramTransport | None = None

    # asyncio protocol

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        self.feed(data)

    def error_received(self, exc: Exception) -> None:
        _LOGGER.debug("telemetry socket of %s: %s", self.platform_id, exc)

    # sans-IO core

    def feed(self, data: bytes, now: float | None = None) -> bool:
        """One datagram; returns whether it was accepted."""
        now = self._clock() if now is None else now
        frames = self.decoder.feed(data)
        if not frames:
            return False
        frame = frames[0]
        self.snapshot.update(frame.sections)
        self.platform_time = frame.timestamp
        self.bytes_received += frame.size
        self.max_datagram = max(self.max_datagram, frame.size)
        self.stats.accepted(frame.seq, now)
        self.tick(now)
        return True

    def tick(self, now: float | None = None) -> list[Change]:
        """Re-evaluate the annunciator (silence grows without datagrams)."""
        now = self._clock() if now is None else now
        changes = self.annunciator.evaluate(
            self.snapshot, self.stats.loss_pct, self.stats.silence(now), now
        )
        self._announce(changes)
        return changes

    def close(self) -> None:
        """Clear every warning (announced) and close the socket. Idempotent."""
        self._announce(self.annunciator.clear_all())
        if self.transport is not None:
            self.transport.close()
            self.transport = None

    def _announce(self, changes: list[Change]) -> None:
        for change in changes:
            warning = change.warning
            log = _LOGGER.warning if change.active else _LOGGER.info
            log(
                "%s: %s %s",
                self.platform_id,
                "WARNING" if change.active else "cleared:",
                warning.message,
            )
            self._publish(
                StationNotification(
                    warning.code,
                    self.platform_id,
                    warning.name,
                    change.active,
                    warning.message,
                    self._wall_clock(),
                )
            )

    def link(self, now: float | None = None) -> dict[str, Any]:
        now = self._clock() if now is None else now
        silence = self.stats.silence(now)
        return {
            "received": self.stats.received,
            "rejected": {k: v for k, v in self.decoder.rejected.items()},
            "rejected_total": sum(self.decoder.rejected.values()),
            "loss_pct": self.stats.loss_pct,
            "silence_s": None if silence is None else round(silence, 2),
            "last_seq": self.stats.last_seq,
            "bytes_received": self.bytes_received,
            "max_datagram": self.max_datagram,
            "round_trip_ms": None if self.round_trip_ms is None else round(self.round_trip_ms, 2),
            "error": self.error,
        }

    def report(self, now: float | None = None) -> dict[str, Any]:
        now = self._clock() if now is None else now
        self.tick(now)
        return {
            "platform_id": self.platform_id,
            "snapshot": self.snapshot,
            "platform_time": self.platform_time,
            "link": self.link(now),
            "warnings": [w.as_dict() for w in self.annunciator.active.values()],
        }


# --------------------------------------------------------------------------- the actor


@dataclass(eq=False)
class _Worker:
    connection: Any
    link: TelemetryLink
    task: asyncio.Task[None] | None = None


class TelemetryReceiver(Actor):
    """Runs one :class:`TelemetryLink` per connected platform."""

    name = "telemetry"

    def __init__(self, ctx: StationContext) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self.notifications: collections.deque[StationNotification] = collections.deque(
            maxlen=NOTIFICATIONS_KEPT
        )
        self._group: asyncio.TaskGroup | None = None
        self._workers: dict[str, _Worker] = {}

    @property
    def links(self) -> dict[str, TelemetryLink]:
        return {platform_id: worker.link for platform_id, worker in self._workers.items()}

    async def run(self) -> None:
        self.subscribe(topics.PLATFORM_CONNECTED, self._on_connected)
        self.subscribe(topics.PLATFORM_DISCONNECTED, self._on_disconnected)
        self.subscribe(topics.STATION_NOTIFICATIONS, self.notifications.append)
        try:
            async with asyncio.TaskGroup() as group:
                self._group = group
                for connection in list(self.ctx.connections.values()):
                    self._on_connected(connection)
                await wait_forever()
        finally:
            self._group = None
            for worker in self._workers.values():
                worker.link.close()
            self._workers.clear()

    def _on_connected(self, connection: Any) -> None:
        if self._group is None:
            return
        platform_id = connection.platform_id
        self._stop(platform_id)
        link = TelemetryLink(
            platform_id,
            connection.session_key,
            self.ctx.config.telemetry,
            lambda note: self.bus.publish(topics.STATION_NOTIFICATIONS, note),
        )
        link.stats.start(time.monotonic())
        worker = _Worker(connection, link)
        self._workers[platform_id] = worker
        worker.task = self._group.create_task(self._serve(worker), name=f"telemetry:{platform_id}")

    def _on_disconnected(self, connection: Any) -> None:
        worker = self._workers.get(connection.platform_id)
        if worker is not None and worker.connection is connection:
            self._stop(connection.platform_id)

    def _stop(self, platform_id: str) -> None:
        worker = self._workers.pop(platform_id, None)
        if worker is None:
            return
        if worker.task is not None and worker.task is not asyncio.current_task():
            worker.task.cancel("platform disconnected")
        worker.link.close()

    async def _serve(self, worker: _Worker) -> None:
        connection, link = worker.connection, worker.link
        config = self.ctx.config.telemetry
        loop = asyncio.get_running_loop()
        host = receive_host(config.bind_host, connection.platform_host)
        try:
            await loop.create_datagram_endpoint(lambda: link, local_addr=(host, 0))
        except OSError as err:
            link.error = f"cannot receive telemetry on {host}: {err.strerror}"
            _LOGGER.error("%s: %s", connection.platform_id, link.error)
            return
        assert link.transport is not None
        port = link.transport.get_extra_info("sockname")[1]
        params: dict[str, Any] = {"port": port}
        if config.rate_hz > 0:
            params["rate_hz"] = config.rate_hz
        if not _wildcard(host) and not _loopback(connection.platform_host):
            params["host"] = host
        link.stats.start(time.monotonic())
        requested = await self._request(connection, link, params)
        again_after = REQUEST_AGAIN_FACTOR * config.silence_s
        while not connection.closed.is_set():
            link.round_trip_ms = connection.round_trip_ms
            link.tick()
            silence = link.stats.silence(time.monotonic())
            if silence is not None and silence > again_after:
                if time.monotonic() - requested > again_after:
                    # The platform lost our stream (its telemetry actor restarted): ask again.
                    requested = await self._request(connection, link, params)
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(connection.closed.wait(), TICK)
        if self._workers.get(connection.platform_id) is worker:
            self._stop(connection.platform_id)

    async def _request(self, connection: Any, link: TelemetryLink, params: dict[str, Any]) -> float:
        """Ask the platform to stream to us; returns when it was asked (monotonic)."""
        try:
            await connection.call("request_telemetry", **params)
            link.error = ""
        except (RpcError, ConnectionError) as err:
            link.error = f"request_telemetry refused: {getattr(err, 'message', err)}"
            _LOGGER.warning("%s: %s", connection.platform_id, link.error)
        return time.monotonic()

    # ------------------------------------------------------------------ local API

    async def api_get_telemetry(self, call: CallContext, platform_id: str) -> dict[str, Any]:
        """The platform's latest telemetry, link figures and active warnings (connects first)."""
        worker = self._workers.get(platform_id)
        if worker is None:
            await self.ctx.connection(platform_id)
            worker = self._workers.get(platform_id)
            if worker is None:
                raise RpcError(UNAVAILABLE, f"no telemetry from {platform_id}")
        return worker.link.report()

    async def api_telemetry_notifications(
        self, call: CallContext, limit: int = 20
    ) -> list[dict[str, Any]]:
        """The most recent notifications, oldest first."""
        items = list(self.notifications)[-limit:] if limit > 0 else []
        return [note.as_dict() for note in items]


def receive_host(configured: str, platform_host: str) -> str:
    """Where to bind: the configured address, else loopback for a platform on loopback."""
    if configured:
        return configured
    return "127.0.0.1" if _loopback(platform_host) else "0.0.0.0"


def _loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _wildcard(host: str) -> bool:
    return host in ("0.0.0.0", "::", "")


async def async_setup(ctx: StationContext) -> None:
    receiver = TelemetryReceiver(ctx)
    ctx.api.add("get_telemetry", receiver.api_get_telemetry, session_required=False)
    ctx.api.add(
        "telemetry_notifications", receiver.api_telemetry_notifications, session_required=False
    )
    ctx.supervisor.start(receiver)
