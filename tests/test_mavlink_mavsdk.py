"""MAVSDK (the ``mavsdk`` wheel, its bundled C++ library) against a --sim platform's MAVLink
endpoint: it connects, imports a QGroundControl ``.plan``, uploads its mission and geofence,
downloads both back, starts the mission and reads the position."""

from __future__ import annotations

import asyncio
import contextlib
import json
import math
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from conftest import free_udp_port, until_armable, wait_until
from mavlink_gcs import LAT, LON, sim_rover_config
from mavlink_gcs import at as position
from mavsdk.asyncio import ComponentType, Configuration, Mavsdk
from mavsdk.asyncio.plugins.mission import MissionAsync, MissionItem, MissionPlan
from mavsdk.asyncio.plugins.mission_raw import MissionRawAsync
from mavsdk.asyncio.plugins.telemetry import TelemetryAsync

from brasidas import topics
from brasidas.messages import PatrolState
from platformd.app import PlatformDaemon


def at(east: float, north: float) -> list[float]:
    return list(position(east, north))


def qgc_plan() -> dict[str, Any]:
    """A plan as QGroundControl saves it: four waypoints, a boundary, a keep-out polygon and
    an exclusion circle."""
    items = [
        {
            "type": "SimpleItem",
            "autoContinue": True,
            "command": 16,
            "doJumpId": index,
            "frame": 3,
            "params": [0, 0, 0, None, *point, 0],
            "AltitudeMode": 1,
            "Altitude": 0,
            "AMSLAltAboveTerrain": None,
        }
        for index, point in enumerate([at(0, 0), at(40, 0), at(40, 30), at(0, 30)], start=1)
    ]
    return {
        "fileType": "Plan",
        "groundStation": "QGroundControl",
        "version": 1,
        "mission": {
            "version": 2,
            "firmwareType": 3,
            "vehicleType": 10,
            "cruiseSpeed": 1.6,
            "hoverSpeed": 1,
            "plannedHomePosition": [LAT, LON, 0],
            "items": items,
        },
        "geoFence": {
            "version": 2,
            "polygons": [
                {
                    "inclusion": True,
                    "version": 1,
                    "polygon": [at(-12, -12), at(52, -12), at(52, 42), at(-12, 42)],
                },
                {"inclusion": False, "version": 1, "polygon": [at(30, 12), at(34, 12), at(34, 16)]},
            ],
            "circles": [
                {"inclusion": False, "version": 1, "circle": {"center": at(20, 15), "radius": 6}}
            ],
        },
        "rallyPoints": {"version": 2, "points": []},
    }


def patrolling(daemon: PlatformDaemon) -> bool:
    status = daemon.bus.last(topics.PATROL_STATUS)
    return status is not None and status.state is PatrolState.PATROLLING


def raw(items: list[Any]) -> list[tuple[int, int, int, int, float]]:
    return [(item.seq, item.command, item.x, item.y, item.param1) for item in items]


async def test_mavsdk_uploads_a_qgc_plan_downloads_it_and_starts_the_mission(
    platform_factory: Callable[..., Awaitable[PlatformDaemon]], tmp_path: Path
) -> None:
    port = free_udp_port()
    daemon = await platform_factory(
        sim_rover_config(tmp_path, port, "mavlink.allow_unsigned_control=true"), None
    )
    patrol = daemon.ctx.patrol
    assert patrol is not None
    plan = tmp_path / "field.plan"
    plan.write_text(json.dumps(qgc_plan()))

    configuration = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(configuration) as mavsdk:
        await mavsdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = await mavsdk.first_autopilot(timeout_s=30.0)
        assert system is not None
        missions = MissionRawAsync(system)
        imported = await missions.import_qgroundcontrol_mission(str(plan))
        assert len(imported.mission_items) == 5  # home, then the four waypoints
        await missions.upload_mission(imported.mission_items)
        await missions.upload_geofence(imported.geofence_items)
        assert patrol.core.route.stops == 4
        area = patrol.core.area
        assert area is not None
        assert sorted(area.keepouts) == ["fence-1", "fence-2"]

        assert raw(await missions.download_mission()) == raw(imported.mission_items)
        assert raw(await missions.download_geofence()) == raw(imported.geofence_items)

        # The position (once the simulated receiver has a fix), then the patrol.
        telemetry = TelemetryAsync(system)
        async for position in telemetry.subscribe_position():
            if math.isfinite(position.latitude_deg):
                break
        assert abs(position.latitude_deg - LAT) < 1e-3
        assert abs(position.longitude_deg - LON) < 1e-3

        # The pre-arm checks passed first, as a pilot waits for them (the start arms through
        # them; the simulated controller may answer seconds late on a loaded machine).
        await until_armable(daemon.ctx)
        await missions.start_mission()
        await wait_until(lambda: patrolling(daemon), timeout=10)


async def test_mavsdk_health_all_ok_is_true_exactly_when_arming_would_pass(
    platform_factory: Callable[..., Awaitable[PlatformDaemon]], tmp_path: Path
) -> None:
    """Issue 27: a script's ``health_all_ok`` wait ends on a healthy rover; without a GPS fix
    it is false and a STATUSTEXT says why; arm, disarm and kill do what they say."""
    from mavsdk.asyncio.plugins.action import ActionAsync, ActionError

    port = free_udp_port()
    daemon = await platform_factory(
        sim_rover_config(tmp_path, port, "mavlink.allow_unsigned_control=true", "imu.enabled=true"),
        None,
    )
    arming = daemon.ctx.arming
    assert arming is not None
    configuration = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(configuration) as mavsdk:
        await mavsdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = await mavsdk.first_autopilot(timeout_s=30.0)
        assert system is not None
        telemetry, action = TelemetryAsync(system), ActionAsync(system)
        async for ok in telemetry.subscribe_health_all_ok():
            if ok:
                break
        assert arming.reasons() == ()
        async for armed in telemetry.subscribe_armed():
            assert not armed  # disarmed at start
            break
        await action.arm()
        await wait_until(lambda: arming.armed)
        async for armed in telemetry.subscribe_armed():
            if armed:
                break
        await action.disarm()
        await wait_until(lambda: not arming.armed)
        await action.arm()
        await action.kill()  # force-disarm (21196)
        await wait_until(lambda: not arming.armed)
        assert arming.last_word is not None
        assert arming.last_word.word == "disarm"

        # The receiver goes silent: not armable, and the reason in a STATUSTEXT.
        texts: list[str] = []

        async def collect() -> None:
            async for text in telemetry.subscribe_status_text():
                texts.append(text.text)

        collecting = asyncio.create_task(collect())
        try:
            assert daemon.ctx.sim.gps is not None
            daemon.ctx.sim.gps.close()
            async for ok in telemetry.subscribe_health_all_ok():
                if not ok:
                    break
            await wait_until(lambda: "PreArm: no GPS fix" in texts, 10)
            with pytest.raises(ActionError):
                await action.arm()
            assert not arming.armed
        finally:
            collecting.cancel("test over")
            with contextlib.suppress(asyncio.CancelledError):
                await collecting


def mission_item(lat: float, lon: float, speed: float | None) -> Any:
    nan = float("nan")
    return MissionItem(
        lat,
        lon,
        0.0,
        nan if speed is None else speed,
        True,
        nan,
        nan,
        MissionItem.CameraAction.NONE,
        nan,
        nan,
        nan,
        nan,
        nan,
        MissionItem.VehicleAction.NONE,
    )


async def test_mavsdks_mission_plugin_keeps_every_waypoint_and_its_speed(
    platform_factory: Callable[..., Awaitable[PlatformDaemon]], tmp_path: Path
) -> None:
    """Its plugin sends the first waypoint as item 0 in a relative frame, and a DO_CHANGE_SPEED
    after each waypoint whose speed is set: four waypoints, four driven, at that speed."""
    port = free_udp_port()
    daemon = await platform_factory(
        sim_rover_config(tmp_path, port, "mavlink.allow_unsigned_control=true"), None
    )
    patrol = daemon.ctx.patrol
    assert patrol is not None
    corners = [position(0, 0), position(40, 0), position(40, 30), position(0, 30)]
    configuration = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(configuration) as mavsdk:
        await mavsdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = await mavsdk.first_autopilot(timeout_s=30.0)
        assert system is not None
        plugin = MissionAsync(system)
        await plugin.upload_mission(MissionPlan([mission_item(*c, None) for c in corners]))
        route = patrol.core.route
        assert len(route.waypoints) == 4  # the first is a waypoint, not home
        for waypoint, corner in zip(route.waypoints, corners, strict=True):
            assert math.dist((waypoint.latitude, waypoint.longitude), corner) < 1e-6
        await plugin.upload_mission(MissionPlan([mission_item(*c, 0.75) for c in corners]))
        route = patrol.core.route
        assert len(route.waypoints) == 4
        # The speed set after the first waypoint is the speed of the legs after it.
        assert [w.speed for w in route.waypoints] == [None, 0.75, 0.75, 0.75]


async def test_mavsdk_sets_fence_options_and_its_geofence_is_a_union(
    platform_factory: Callable[..., Awaitable[PlatformDaemon]], tmp_path: Path
) -> None:
    """MAVSDK's Param plugin sets FENCE_OPTIONS (an INT16, C-cast), then its Geofence plugin
    uploads two overlapping inclusion polygons: the map's boundary is their union."""
    from mavsdk.asyncio.plugins.geofence import (
        FenceType,
        GeofenceAsync,
        GeofenceData,
        Point,
        Polygon,
    )
    from mavsdk.asyncio.plugins.param import ParamAsync

    port = free_udp_port()
    daemon = await platform_factory(
        sim_rover_config(tmp_path, port, "mavlink.allow_unsigned_control=true"), None
    )
    patrol = daemon.ctx.patrol
    assert patrol is not None

    def field(west: float, east: float) -> Polygon:
        corners = [at(west, -12), at(east, -12), at(east, 42), at(west, 42)]
        return Polygon([Point(lat, lon) for lat, lon in corners], FenceType.INCLUSION)

    configuration = Configuration.create_with_component_type(ComponentType.GROUND_STATION)
    async with Mavsdk(configuration) as mavsdk:
        await mavsdk.add_any_connection(f"udpin://127.0.0.1:{port}")
        system = await mavsdk.first_autopilot(timeout_s=30.0)
        assert system is not None
        params = ParamAsync(system)
        await params.set_param_int("FENCE_OPTIONS", 2)
        assert await params.get_param_int("FENCE_OPTIONS") == 2
        await GeofenceAsync(system).upload_geofence(
            GeofenceData([field(-12, 45), field(-5, 52)], [])
        )
    area = patrol.core.area
    assert area is not None
    for east in (-10, 48):  # each inside one field only
        assert area.inside(*area.local(*position(east, 15)))
