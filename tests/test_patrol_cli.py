"""``brasidas-station map / route / patrol`` through the station daemon to a --sim platform."""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable
from pathlib import Path

from support.cli import run_cli
from support.connected import connected

from brasidas import topics
from platformd.app import PlatformDaemon
from platformd.sim.demo_area import demo_map
from stationd.daemon import StationDaemon

Factory = Callable[..., Awaitable[PlatformDaemon]]
LAT, LON = 37.9415, 23.6530


async def test_map_route_and_patrol_commands(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    await connected(station, platform_factory, fleet_key, tmp_path, platform_id="rover-5")

    good = tmp_path / "field.geojson"
    good.write_text(json.dumps(demo_map(LAT, LON)))
    code, out, _ = await run_cli(station, "map", "rover-5", str(good))
    assert code == 0
    assert "map 'demo field' loaded" in out
    assert "1 keep-out zones" in out

    bad = demo_map(LAT, LON)
    ring = bad["features"][1]["geometry"]["coordinates"][0]
    ring[1], ring[2] = ring[2], ring[1]
    (tmp_path / "bad.geojson").write_text(json.dumps(bad))
    code, out, err = await run_cli(station, "map", "rover-5", str(tmp_path / "bad.geojson"))
    assert code == 1
    assert "map refused" in err
    assert "self-intersection" in err
    far = tmp_path / "far.geojson"
    far.write_text(json.dumps(demo_map(LAT + 0.01, LON)))
    code, _, err = await run_cli(station, "map", "rover-5", str(far))
    assert code == 1
    assert "outside the map's boundary" in err

    code, out, _ = await run_cli(station, "route", "rover-5", "sw", "se", "ne", "sw")
    assert code == 0
    assert "4 waypoints set (closed, loops)" in out
    route_file = tmp_path / "route.txt"
    route_file.write_text(f"# out and back\n{LAT},{LON}\nne\n")
    code, out, _ = await run_cli(station, "route", "rover-5", str(route_file), "--json")
    answer = json.loads(out)
    assert code == 0
    assert answer["closed"] is False
    assert answer["waypoints"][1]["name"] == "ne"
    code, _, err = await run_cli(station, "route", "rover-5", "sw", "91,0")
    assert code == 1
    assert "waypoint 2: 91.0, 0.0 is not a latitude" in err

    code, out, _ = await run_cli(station, "patrol", "rover-5", "--json")
    state = json.loads(out)
    assert code == 0
    assert {"state", "waypoint", "distance_m", "lap", "reason"} <= set(state)
    assert state["state"] == "stopped"
    assert state["waypoints"] == 2
    code, out, _ = await run_cli(station, "patrol", "rover-5", "start")
    assert code == 0
    assert out.split()[1] in ("patrolling", "holding")
    code, out, _ = await run_cli(station, "patrol", "rover-5", "stop")
    assert code == 0
    assert "state      stopped" in out
    assert "stopped by the operator" in out

    # ...and `status` shows the patrol, the pose and the automations (telemetry).
    async def shown() -> str:
        _, out, _ = await run_cli(station, "status", "rover-5")
        return out

    text = ""
    for _ in range(50):
        text = await shown()
        if "stopped by the operator" in text:
            break
    assert "autonomy   stopped  waypoint 1/2" in text
    assert "(stopped by the operator)" in text
    assert "pose       37.94" in text
    assert "patrol on" in text


async def test_a_town_of_a_thousand_buildings_loads_and_a_too_big_map_says_its_size(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    from support.maps import drivable_town

    from brasidas.limits import MAP_REQUEST_MAX_BYTES, STATION_API_MAX_BYTES

    platform = await connected(
        station, platform_factory, fleet_key, tmp_path, platform_id="rover-6"
    )
    pose = platform.bus.last(topics.POSE)
    assert pose is not None
    town = drivable_town(pose.latitude, pose.longitude, buildings=1000)
    text = json.dumps(town)
    assert len(text) > 250_000  # the maps: 266 KB and up failed with a 413
    (tmp_path / "town.geojson").write_text(text)
    code, out, err = await run_cli(station, "map", "rover-6", str(tmp_path / "town.geojson"))
    assert code == 0, err
    assert f"{len(town['features']) - 1} keep-out zones" in out

    # Over the limit: refused before it is sent, with its size and the limit.
    town["name"] = "x" * MAP_REQUEST_MAX_BYTES
    (tmp_path / "huge.geojson").write_text(json.dumps(town))
    code, _, err = await run_cli(station, "map", "rover-6", str(tmp_path / "huge.geojson"))
    assert code == 1
    size = (tmp_path / "huge.geojson").stat().st_size
    assert f"{size} bytes, over the limit of {MAP_REQUEST_MAX_BYTES} bytes" in err
    # The station's own refusal (another client) says so too, as JSON-RPC.
    import aiohttp

    body = (
        b'{"jsonrpc":"2.0","id":1,"method":"map_load","params":"'
        + b"a" * (STATION_API_MAX_BYTES + 10)
        + b'"}'
    )
    async with (
        aiohttp.ClientSession() as session,
        session.post(f"{station.api_url}/api/rpc", data=body) as response,
    ):
        answer = await response.json()
    assert response.status == 413
    assert answer["error"]["message"] == (
        f"request too large: {len(body)} bytes, the limit is {STATION_API_MAX_BYTES} bytes"
    )
