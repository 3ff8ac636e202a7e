"""The station's connection manager: one session per platform, kept alive, closed cleanly.

Local API methods (for the CLI and the browser console) act on a platform by id and connect
to it first when needed, resolving its signaling URL from discovery. A session lost without
the operator's word (heartbeats failing through a long link cut, the platform restarted) is
re-established by itself as soon as the platform answers again — as an observer: the manual
override is never re-engaged by the station, the operator does that deliberately.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
import time
from typing import Any

from brasidas import topics
from brasidas.actor import Actor, wait_forever
from brasidas.annunciator import CONTROL_TAKEN
from brasidas.backoff import Backoff
from brasidas.codecs.commands import (
    MAIN_LIGHTS,
    MANUAL_OVERRIDE,
    OBSERVER_CODES,
    POSITIONAL_LIGHTS,
    CommandCode,
)
from brasidas.codecs.jsonrpc import INVALID_PARAMS, UNAVAILABLE, CallContext, RpcError
from brasidas.messages import CommandReceived, CommandSent, PlatformLink, StationNotification
from stationd.client import CLOSED_BY_STATION, AuthenticationError, PlatformConnection
from stationd.context import StationContext

_LOGGER = logging.getLogger(__name__)

NOT_CONNECTED = -32010
CLOSED_BY_OPERATOR = "closed by operator"
"""With :data:`~stationd.client.CLOSED_BY_STATION`, the close reasons after which the session
is not re-established (any other is a loss)."""
MAX_PLATFORM_ID = 64
"""Characters in a platform id the local API is asked about, at most (a beacon holds one in
100 bytes with the rest): a longer one is refused before anything is looked up or kept."""
RECONNECT_INITIAL = 0.5
RECONNECT_MAX = 5.0
"""Seconds between attempts to re-establish a lost session (capped exponential backoff)."""


class ConnectionManager(Actor):
    name = "connections"

    def __init__(self, ctx: StationContext) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self._watchers: asyncio.TaskGroup | None = None
        self._connecting: dict[str, tuple[asyncio.Lock, int]] = {}
        """Per platform being connected: its lock and how many callers want it."""
        self._reconnecting: dict[str, str] = {}
        """Platforms whose lost session is being re-established, with their signaling URL."""
        self._stopping = False
        """The station is stopping: no session is opened any more. Other actors still run
        while the stop hooks do, and one asking for a platform then (Foxglove live fetching a
        grid) opened a session nothing would close, its heartbeat task left running."""

    async def run(self) -> None:
        async with asyncio.TaskGroup() as watchers:
            self._watchers = watchers
            try:
                await wait_forever()
            finally:
                self._watchers = None

    async def async_stop(self) -> None:
        """Close every session: platforms release the manual override at once (R-17)."""
        self._stopping = True
        await asyncio.gather(
            *(connection.close() for connection in list(self.ctx.connections.values())),
            return_exceptions=True,
        )

    # ------------------------------------------------------------------ connections

    async def ensure(self, platform_id: str, url: str = "") -> PlatformConnection:
        """The open connection to ``platform_id``, connecting first if needed."""
        check_platform_id(platform_id)
        existing = self.ctx.connections.get(platform_id)
        if existing is not None and not existing.closed.is_set():
            return existing
        # One attempt at a time per platform; the lock lives while someone wants it, so ids
        # asked about (known or not) leave nothing behind.
        lock, wanted = self._connecting.get(platform_id, (asyncio.Lock(), 0))
        self._connecting[platform_id] = (lock, wanted + 1)
        try:
            async with lock:
                return await self._connect(platform_id, url)
        finally:
            lock, wanted = self._connecting[platform_id]
            if wanted == 1:
                del self._connecting[platform_id]
            else:
                self._connecting[platform_id] = (lock, wanted - 1)

    async def _connect(self, platform_id: str, url: str) -> PlatformConnection:
        """:meth:`ensure`'s work, under the platform's lock."""
        existing = self.ctx.connections.get(platform_id)
        if existing is not None and not existing.closed.is_set():
            return existing
        self._refuse_if_stopping(platform_id)
        url = url or await self._resolve(platform_id)
        connection = PlatformConnection(
            platform_id,
            url,
            station_id=self.ctx.config.station.id,
            fleet_key=self.ctx.fleet_key,
            timeout=self.ctx.config.station.connect_timeout,
        )
        try:
            await connection.open()
        except AuthenticationError as err:
            raise RpcError(UNAVAILABLE, f"{platform_id}: {err}") from None
        except (OSError, TimeoutError, RpcError) as err:
            raise RpcError(UNAVAILABLE, f"{platform_id}: cannot connect to {url}: {err}") from None
        if self._stopping:  # the stop hook ran while this one was opening: it missed it
            await connection.close()
            self._refuse_if_stopping(platform_id)
        connection.on_control_lost = functools.partial(self._on_control_lost, platform_id)
        self.ctx.connections[platform_id] = connection
        if self._watchers is not None:
            self._watchers.create_task(self._watch(connection), name=f"watch:{platform_id}")
        _LOGGER.info("connected to %s at %s", platform_id, url)
        self.bus.publish(
            topics.PLATFORM_CONNECTED, PlatformLink(platform_id, connection.session_id)
        )
        return connection

    def _refuse_if_stopping(self, platform_id: str) -> None:
        if self._stopping:
            raise RpcError(UNAVAILABLE, f"{platform_id}: the station is stopping")

    async def _resolve(self, platform_id: str) -> str:
        if self.ctx.api.has("list_platforms"):
            for entry in await self.ctx.api.call_local("list_platforms"):
                if entry.get("id") == platform_id:
                    return str(entry["url"])
        raise RpcError(UNAVAILABLE, f"platform {platform_id} not discovered (is it online?)")

    async def _watch(self, connection: PlatformConnection) -> None:
        await connection.closed.wait()
        platform_id = connection.platform_id
        if self.ctx.connections.get(platform_id) is connection:
            del self.ctx.connections[platform_id]
        _LOGGER.warning("connection to %s ended: %s", platform_id, connection.close_reason)
        with contextlib.suppress(Exception):
            await connection.close()
        self.bus.publish(
            topics.PLATFORM_DISCONNECTED,
            PlatformLink(platform_id, connection.session_id, connection.close_reason),
        )
        if connection.close_reason not in (CLOSED_BY_OPERATOR, CLOSED_BY_STATION):
            await self._reconnect(platform_id, connection.signaling_url)

    async def _reconnect(self, platform_id: str, url: str) -> None:
        """Connect again until the platform answers (or the operator connects or disconnects
        it meanwhile). The new session holds nothing: not the override, not control."""
        backoff = Backoff(RECONNECT_INITIAL, RECONNECT_MAX)
        self._reconnecting[platform_id] = url
        try:
            while self._reconnecting.get(platform_id) == url:
                await asyncio.sleep(backoff.next())
                if self._reconnecting.get(platform_id) != url:
                    return
                try:
                    await self.ensure(platform_id, url)
                except RpcError as err:
                    if backoff.attempts == 1:
                        _LOGGER.info("reconnecting to %s: %s", platform_id, err.message)
                    continue
                _LOGGER.info(
                    "reconnected to %s (as an observer until the operator engages)", platform_id
                )
                return
        finally:
            if self._reconnecting.get(platform_id) == url:
                del self._reconnecting[platform_id]

    def _on_control_lost(self, platform_id: str, holder: str | None) -> None:
        message = (
            f"control of {platform_id} taken by station {holder}"
            if holder
            else f"control of {platform_id} lost"
        )
        _LOGGER.warning("%s", message)
        self.bus.publish(
            topics.STATION_NOTIFICATIONS,
            StationNotification(
                CONTROL_TAKEN, platform_id, "control_taken", True, message, time.time()
            ),
        )

    def connected(self, platform_id: str) -> PlatformConnection:
        check_platform_id(platform_id)
        connection = self.ctx.connections.get(platform_id)
        if connection is None or connection.closed.is_set():
            raise RpcError(NOT_CONNECTED, f"not connected to {platform_id}")
        return connection

    # ------------------------------------------------------------------ local API

    async def api_connect(
        self, call: CallContext, platform_id: str, url: str = ""
    ) -> dict[str, Any]:
        return (await self.ensure(platform_id, url)).summary()

    async def api_disconnect(self, call: CallContext, platform_id: str) -> bool:
        reconnecting = self._reconnecting.pop(platform_id, None) is not None
        connection = self.ctx.connections.get(platform_id)
        if connection is None:
            return reconnecting
        connection.close_reason = CLOSED_BY_OPERATOR
        await connection.close()
        return True

    async def api_connections(self, call: CallContext) -> list[dict[str, Any]]:
        return [connection.summary() for connection in self.ctx.connections.values()]

    async def api_status(self, call: CallContext, platform_id: str) -> dict[str, Any]:
        connection = await self.ensure(platform_id)
        summary = connection.summary()
        summary["report"] = await connection.call("get_telemetry_report")
        return summary

    async def api_command(
        self, call: CallContext, platform_id: str, group: int, command: int, payload: str = ""
    ) -> dict[str, Any]:
        connection = await self.ensure(platform_id)
        code = CommandCode(group, command)
        try:
            answer: dict[str, Any] = await connection.call(
                "issue_system_command", group=group, command=command, payload=payload
            )
        except RpcError as err:
            self._sent(platform_id, code, payload, False, err.message)
            raise
        accepted = bool(answer.get("accepted"))
        self._sent(platform_id, code, payload, accepted, str(answer.get("reason") or ""))
        if accepted and code not in OBSERVER_CODES:
            connection.control = True  # a control command went through: this station holds it
        return answer

    def _sent(self, platform_id: str, code: CommandCode, payload: str, ok: bool, why: str) -> None:
        """Tell the bus what this station sent for its operator (Foxglove's ``/commands``;
        without the session token, which opens downloads)."""
        station = self.ctx.config.station.id
        command = CommandReceived("system", str(code), payload, None, station, ok, why)
        self.bus.publish(topics.COMMAND_SENT, CommandSent(platform_id, command))

    async def api_movrd(
        self, call: CallContext, platform_id: str, engaged: bool, force: bool = False
    ) -> dict[str, Any]:
        """Engage or release the override; ``force`` takes control from another station."""
        payload = f"state={engaged},force=yes" if force and engaged else str(engaged)
        answer = await self.api_command(
            call, platform_id, MANUAL_OVERRIDE.group, MANUAL_OVERRIDE.command, payload
        )
        if answer.get("accepted"):
            self.connected(platform_id).manual_override = engaged
        return answer

    async def api_lights(
        self, call: CallContext, platform_id: str, which: str, on: bool
    ) -> dict[str, Any]:
        codes = {"main": MAIN_LIGHTS, "pos": POSITIONAL_LIGHTS, "positional": POSITIONAL_LIGHTS}
        code = codes.get(which)
        if code is None:
            raise RpcError(INVALID_PARAMS, "invalid params: which must be main or pos")
        return await self.api_command(
            call, platform_id, code.group, code.command, "ON" if on else "OFF"
        )


def check_platform_id(platform_id: str) -> None:
    """-32602 for an id no platform can have (longer than :data:`MAX_PLATFORM_ID`)."""
    if len(platform_id) > MAX_PLATFORM_ID:
        raise RpcError(
            INVALID_PARAMS, f"invalid params: platform_id longer than {MAX_PLATFORM_ID} characters"
        )


async def async_setup(ctx: StationContext) -> None:
    manager = ConnectionManager(ctx)
    ctx.connection_manager = manager
    for name in ("connect", "disconnect", "connections", "status", "command", "movrd", "lights"):
        ctx.api.add(name, getattr(manager, f"api_{name}"), session_required=False)
    ctx.supervisor.start(manager)
