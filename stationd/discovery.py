"""Discovery (R-9) in the station: the list of platforms online, served to the CLI and console.

The directory and listener are :mod:`brasidas.discovery` (platforms keep the same list);
here they get the station's settings (``discovery.*``) and the daemon serves the list as the
``list_platforms`` API method. ``brasidas-station list`` uses :func:`discover` on its own
socket (the port is shared with ``SO_REUSEPORT``; beacons go to a broadcast address or a
multicast group, so every listener on the host hears them).
"""

from __future__ import annotations

from typing import Any

from brasidas import discovery, topics
from brasidas.codecs.jsonrpc import CallContext
from brasidas.config import StationConfig
from brasidas.messages import PlatformLink
from stationd.context import StationContext


def listen_settings(config: StationConfig) -> discovery.ListenSettings:
    section = config.discovery
    return discovery.ListenSettings(
        port=section.port,
        host=section.bind_host,
        groups=tuple(section.groups),
        interfaces=tuple(section.interfaces),
        expiry=section.expiry,
    )


async def discover(config: StationConfig, key: bytes | None, wait: float) -> list[dict[str, Any]]:
    """Listen for ``wait`` seconds on the discovery port; the platforms heard, as dicts."""
    return await discovery.discover(listen_settings(config), key, wait)


async def async_setup(ctx: StationContext) -> None:
    settings = listen_settings(ctx.config)
    directory = discovery.PlatformDirectory(ctx.fleet_key, settings.expiry)
    ctx.supervisor.start(discovery.BeaconListener(ctx.bus, directory, settings))

    def on_connected(link: PlatformLink) -> None:
        """A platform's signed boot announcement: its beacons of that boot are taken."""
        connection = ctx.connections.get(link.platform_id)
        if connection is not None and connection.boot is not None:
            directory.announce_boot(link.platform_id, connection.boot)

    # The station's lifetime: the bus and the directory end with the daemon.
    ctx.bus.subscribe(topics.PLATFORM_CONNECTED, on_connected)

    async def list_platforms(call: CallContext) -> list[dict[str, Any]]:
        """The platforms online (heard within ``discovery.expiry`` seconds)."""
        return directory.entries()

    async def discovery_stats(call: CallContext) -> dict[str, Any]:
        """Beacons received, accepted and dropped by reason."""
        return directory.stats()

    ctx.api.add("list_platforms", list_platforms, session_required=False)
    ctx.api.add("discovery_stats", discovery_stats, session_required=False)
