"""What every station subsystem gets at setup."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

from brasidas.actor import Supervisor
from brasidas.bus import Bus
from brasidas.codecs.jsonrpc import UNAVAILABLE, Dispatcher, RpcError
from brasidas.config import StationConfig
from brasidas.messages import Velocity
from stationd.client import PlatformConnection
from stationd.video_feed import Feed


class Connector(Protocol):
    """What the context needs of the connection manager (stationd.connections)."""

    async def ensure(self, platform_id: str, url: str = "") -> PlatformConnection:
        """The open connection to ``platform_id``, connecting first if needed."""
        ...


class DriveInputs(Protocol):
    """What the context needs of the teleop actor (stationd.teleop)."""

    def set_drive(self, platform_id: str, velocity: Velocity) -> None:
        """The operator's velocity for ``platform_id`` now (it lapses unless repeated)."""
        ...


class VideoFeeds(Protocol):
    """What other subsystems use of the console's video feeds (stationd.console)."""

    async def open_feed(self, platform_id: str, stream: str = "navcam") -> Feed:
        """The platform's feed, started if needed; add a viewer to ``feed.fanout``."""
        ...

    def release_feed(self, platform_id: str, stream: str = "navcam") -> None:
        """A viewer added to the feed left."""
        ...


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
    connection_manager: Connector | None = None
    """Set by stationd.connections: ``await ctx.connection_manager.ensure(platform_id)``."""
    teleop: DriveInputs | None = None
    """Set by stationd.teleop: the velocity senders and the operator's drive inputs."""
    video_feeds: VideoFeeds | None = None
    """Set by stationd.console: the platforms' video feeds, received once, shared."""

    async def connection(self, platform_id: str) -> PlatformConnection:
        """The open connection to ``platform_id``, connecting first if needed."""
        if self.connection_manager is None:
            raise RpcError(UNAVAILABLE, f"not connected to {platform_id}")
        return await self.connection_manager.ensure(platform_id)
