"""The station's connection manager: one session per platform, kept alive, closed cleanly.

Local API methods (for the CLI and the browser console) act on a platform by id and connect
to it first when needed, resolving its signaling URL from discovery.
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
from brasidas.codecs.commands import (
    MAIN_LIGHTS,
    MANUAL_OVERRIDE,
    OBSERVER_CODES,
    POSITIONAL_LIGHTS,
    CommandCode,
)
from brasidas.codecs.jsonrpc import INVALID_PARAMS, UNAVAILABLE, CallContext, RpcError
from brasidas.messages import PlatformLink, StationNotification
from stationd.client import AuthenticationError, PlatformConnection
from stationd.context import StationContext
from stationd.telemetry.annunciator import CONTROL_TAKEN

_LOGGER = logging.getLogger(__name__)

NOT_CONNECTED = -32010


class ConnectionManager(Actor):
    name = "connections"

    def __init__(self, ctx: StationContext) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self._watchers: asyncio.TaskGroup | None = None
        self._connecting: dict[str, asyncio.Lock] = {}

    async def run(self) -> None:
        async with asyncio.TaskGroup() as watchers:
            self._watchers = watchers
            try:
                await wait_forever()
            finally:
                self._watchers = None

    async def async_stop(self) -> None:
        """Close every session: platforms release the manual override at once (R-17)."""
        await asyncio.gather(
            *(connection.close() for connection in list(self.ctx.connections.values())),
            return_exceptions=True,
        )

    # ------------------------------------------------------------------ connections

    async def ensure(self, platform_id: str, url: str = "") -> PlatformConnection:
        """The open connection to ``platform_id``, connecting first if needed."""
        lock = self._connecting.setdefault(platform_id, asyncio.Lock())
        async with lock:
            existing = self.ctx.connections.get(platform_id)
            if existing is not None and not existing.closed.is_set():
                return existing
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
                raise RpcError(
                    UNAVAILABLE, f"{platform_id}: cannot connect to {url}: {err}"
                ) from None
            connection.on_control_lost = functools.partial(self._on_control_lost, platform_id)
            self.ctx.connections[platform_id] = connection
            if self._watchers is not None:
                self._watchers.create_task(self._watch(connection), name=f"watch:{platform_id}")
            _LOGGER.info("connected to %s at %s", platform_id, url)
            self.bus.publish(
                topics.PLATFORM_CONNECTED, PlatformLink(platform_id, connection.session_id)
            )
            return connection

    async def _resolve(self, platform_id: str) -> str:
        if self.ctx.api.has("list_platforms"):
            for entry in await self.ctx.api.call_local("list_platforms"):
                if entry.get("id") == platform_id:
                    return str(entry["url"])
        raise RpcError(UNAVAILABLE, f"platform {platform_id} not discovered (is it online?)")

    async def _watch(self, connection: PlatformConnection) -> None:
        await connection.closed.wait()
        if self.ctx.connections.get(connection.platform_id) is connection:
            del self.ctx.connections[connection.platform_id]
        _LOGGER.warning(
            "connection to %s ended: %s", connection.platform_id, connection.close_reason
        )
        with contextlib.suppress(Exception):
            await connection.close()
        self.bus.publish(
            topics.PLATFORM_DISCONNECTED,
            PlatformLink(connection.platform_id, connection.session_id, connection.close_reason),
        )

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
        connection = self.ctx.connections.get(platform_id)
        if connection is None:
            return False
        connection.close_reason = "closed by operator"
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
        answer: dict[str, Any] = await connection.call(
            "issue_system_command", group=group, command=command, payload=payload
        )
        if answer.get("accepted") and CommandCode(group, command) not in OBSERVER_CODES:
            connection.control = True  # a control command went through: this station holds it
        return answer

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


async def async_setup(ctx: StationContext) -> None:
    manager = ConnectionManager(ctx)
    ctx.connection_manager = manager
    for name in ("connect", "disconnect", "connections", "status", "command", "movrd", "lights"):
        ctx.api.add(name, getattr(manager, f"api_{name}"), session_required=False)
    ctx.supervisor.start(manager)
