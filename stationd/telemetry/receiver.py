"""The station's telemetry receiver: one :class:`TelemetryLink` per connected platform.

For every connected platform the receiver binds a UDP socket, asks the platform to
``request_telemetry`` to it and runs the link's silence checks; raising and clearing a
warning publishes a group 90 :class:`~brasidas.messages.StationNotification` on the station
bus.

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
from dataclasses import dataclass, field
from typing import Any

from brasidas import topics
from brasidas.actor import Actor, wait_forever
from brasidas.codecs.jsonrpc import UNAVAILABLE, CallContext, RpcError
from brasidas.codecs.telemetry_schema import SCHEMA_VERSION
from brasidas.messages import PlatformLink, StationNotification
from stationd.client import PlatformConnection
from stationd.context import StationContext
from stationd.telemetry.link import TelemetryLink, version_mismatch

_LOGGER = logging.getLogger(__name__)

TICK = 0.1
"""How often silence is checked when no datagram arrives."""
NOTIFICATIONS_KEPT = 100
REQUEST_AGAIN_FACTOR = 3.0
"""After this many ``silence_s`` without data the station asks for its stream again."""


@dataclass(eq=False)
class _Worker:
    connection: PlatformConnection
    link: TelemetryLink
    task: asyncio.Task[None] | None = None
    recheck: asyncio.Event = field(default_factory=asyncio.Event)
    """Telemetry says another station holds the control this one believed it held."""


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
                    self._start(connection)
                await wait_forever()
        finally:
            self._group = None
            for worker in self._workers.values():
                worker.link.close()
            self._workers.clear()

    def _on_connected(self, link: PlatformLink) -> None:
        connection = self.ctx.connections.get(link.platform_id)
        if connection is not None and connection.session_id == link.session_id:
            self._start(connection)

    def _start(self, connection: PlatformConnection) -> None:
        if self._group is None:
            return
        platform_id = connection.platform_id
        self._stop(platform_id)
        link = TelemetryLink(
            platform_id,
            connection.session_key,
            self.ctx.config.telemetry,
            lambda note: self.bus.publish(topics.STATION_NOTIFICATIONS, note),
            on_snapshot=lambda snapshot: self.bus.publish(topics.TELEMETRY_SNAPSHOTS, snapshot),
        )
        link.stats.start(time.monotonic())
        worker = _Worker(connection, link)
        link.on_controller = lambda controller: self._on_controller(worker, controller)
        self._workers[platform_id] = worker
        worker.task = self._group.create_task(self._serve(worker), name=f"telemetry:{platform_id}")

    def _on_controller(self, worker: _Worker, controller: str | None) -> None:
        connection = worker.connection
        if connection.control and controller not in (None, connection.station_id):
            worker.recheck.set()

    def _on_disconnected(self, link: PlatformLink) -> None:
        worker = self._workers.get(link.platform_id)
        if worker is not None and worker.connection.session_id == link.session_id:
            self._stop(link.platform_id)

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
            if worker.recheck.is_set():
                # Control taken (the platform pushed telemetry at once): a heartbeat confirms
                # it — a datagram can be older than this station's own takeover — and tells
                # the operator (90.17) now, not at the next heartbeat.
                worker.recheck.clear()
                with contextlib.suppress(RpcError, ConnectionError):
                    await connection.heartbeat()
            with contextlib.suppress(TimeoutError):
                # Woken early by a recheck; a closed connection ends the worker through
                # PLATFORM_DISCONNECTED (or at the next tick). asyncio.timeout: 3.11's
                # wait_for swallows a cancellation that comes as the event is set.
                async with asyncio.timeout(TICK):
                    await worker.recheck.wait()
        if self._workers.get(connection.platform_id) is worker:
            self._stop(connection.platform_id)

    async def _request(
        self, connection: PlatformConnection, link: TelemetryLink, params: dict[str, Any]
    ) -> float:
        """Ask the platform to stream to us; returns when it was asked (monotonic)."""
        try:
            answer = await connection.call("request_telemetry", **params)
            version = answer.get("version") if isinstance(answer, dict) else None
            link.error = "" if version == SCHEMA_VERSION else version_mismatch(version)
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
