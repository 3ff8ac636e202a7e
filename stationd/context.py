"""What every station subsystem gets at setup."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from brasidas.actor import Supervisor
from brasidas.bus import Bus
from brasidas.codecs.jsonrpc import UNAVAILABLE, Dispatcher, RpcError
from brasidas.config import StationConfig

if TYPE_CHECKING:
    from stationd.client import PlatformConnection
    from stationd.connections import ConnectionManager
    from stationd.teleop import Teleop


@dataclass
class StationContext:
    config: StationConfig
    bus: Bus
    supervisor: Supervisor
    api: Dispatcher
    """The station's local API (CLI and browser console): ``api.add(name, h, session_required=False)``."""
    fleet_key: bytes | None
    connections: dict[str, PlatformConnection] = field(default_factory=dict)
    """Open platform connections by platform id."""
    connection_manager: ConnectionManager | None = None
    """Set by stationd.connections: ``await ctx.connection_manager.ensure(platform_id)``."""
    teleop: Teleop | None = None
    """Set by stationd.teleop: the velocity senders and the operator's drive inputs."""

    async def connection(self, platform_id: str) -> PlatformConnection:
        """The open connection to ``platform_id``, connecting first if needed."""
        if self.connection_manager is None:
            raise RpcError(UNAVAILABLE, f"not connected to {platform_id}")
        return await self.connection_manager.ensure(platform_id)
