"""A station connected to a --sim platform with a map and a route file (the map-file tests)."""

from __future__ import annotations

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
) -> PlatformDaemon:
    platform = await platform_factory(
        quiet_platform_config(
            *settings,
            "platform.id=rover-7",
            "sim.enabled=true",
            "gps.enabled=true",
            "gps.sim_rate_hz=5",
            f"map.file={tmp_path / 'map.geojson'}",
            f"autonomy.route_file={tmp_path / 'route.json'}",
        ),
        fleet_key,
    )
    await wait_until(lambda: platform.bus.last(topics.POSE) is not None, 10)
    code, _, _ = await run_cli(station, "connect", "rover-7", "--url", platform.ctx.signaling_url)
    assert code == 0

    async def position_known() -> bool:
        report = await station.ctx.api.call_local("get_telemetry", platform_id="rover-7")
        return report.get("snapshot", {}).get("pose", {}).get("lat") is not None

    for _ in range(100):  # the order checks need the robot's position at the station
        if await position_known():
            break
        await wait_until(lambda: True, 0.1)
    return platform
