"""What every station subsystem gets at setup."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from brasidas.actor import Supervisor
from brasidas.bus import Bus
from brasidas.codecs.jsonrpc import Dispatcher
from brasidas.config import StationConfig

if TYPE_CHECKING:
    from stationd.client import PlatformConnection


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
    connection_manager: Any = None
    """stationd.connections.ConnectionManager: ``await ctx.connection_manager.ensure(id)``."""
