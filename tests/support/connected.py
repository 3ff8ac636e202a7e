"""A station connected to a --sim platform with a map and a route file (the map, route and
patrol commands' tests)."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from pathlib import Path

from conftest import quiet_platform_config, wait_until

from brasidas import topics
from platformd.app import PlatformDaemon
from stationd.daemon import StationDaemon
from support.cli import run_cli

Factory = Callable[..., Awaitable[PlatformDaemon]]


async def connected(
    station: StationDaemon,
    platform_factory: Factory,
    fleet_key: bytes,
    tmp_path: Path,
    *settings: str,
    platform_id: str = "rover-7",
) -> PlatformDaemon:
    """A --sim platform with a GPS (its map and route files in ``tmp_path``), connected to
    ``station`` with ``brasidas-station connect``, once the station knows its position (the
    map and route checks need it)."""
    platform = await platform_factory(
        quiet_platform_config(
            *settings,
            f"platform.id={platform_id}",
            "sim.enabled=true",
            "gps.enabled=true",
            "gps.sim_rate_hz=5",
            f"map.file={tmp_path / 'map.geojson'}",
            f"autonomy.route_file={tmp_path / 'route.json'}",
        ),
        fleet_key,
    )
    await wait_until(lambda: platform.bus.last(topics.POSE) is not None, 10)
    code, _, _ = await run_cli(station, "connect", platform_id, "--url", platform.ctx.signaling_url)
    assert code == 0

    async def position_known() -> None:
        while True:
            report = await station.ctx.api.call_local("get_telemetry", platform_id=platform_id)
            if report.get("snapshot", {}).get("pose", {}).get("lat") is not None:
                return
            await asyncio.sleep(0.05)

    await asyncio.wait_for(position_known(), 10)
    return platform
