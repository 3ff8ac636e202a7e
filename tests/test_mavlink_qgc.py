"""QGroundControl's connect sequence, replayed from its source with pymavlink and its
timeouts, against a --sim platform over loopback UDP: every step answered at once (no
"Loading parameters" stall, fences on, no firmware popup, the video the spec's way); and
driving from a ground station with RC overrides."""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from conftest import free_udp_port, until_armable, wait_until
from mavlink_gcs import FAST_ROVER, Gcs, at, qgc_connect, sim_rover_config
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas import topics
from brasidas.messages import Velocity
from platformd.app import PlatformDaemon

Factory = Callable[..., Awaitable[PlatformDaemon]]


@pytest.fixture
async def gcs() -> AsyncIterator[Gcs]:
    station = await Gcs.open()
    yield station
    station.close()


async def start(platform_factory: Factory, tmp_path: Path, gcs: Gcs, *overrides: str) -> Any:
    daemon = await platform_factory(sim_rover_config(tmp_path, gcs.port, *overrides), None)
    await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 1)
    gcs.send(
        mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3
        )
    )
    return daemon


async def test_qgroundcontrols_connect_runs_through_without_a_timeout(
    platform_factory: Factory, tmp_path: Path, gcs: Gcs
) -> None:
    await start(platform_factory, tmp_path, gcs)
    started = time.monotonic()
    got = await qgc_connect(gcs)  # any step past QGC's timeout raises TimeoutError
    assert got["params_complete"] - started < 5.0
    # MAVLink 2 known: QGroundControl keeps fences (and asks for them and rally points).
    assert got["PROTOCOL_VERSION_ack"].result == mavlink.MAV_RESULT_ACCEPTED
    assert got["PROTOCOL_VERSION"].version == got["PROTOCOL_VERSION"].max_version == 200
    assert got["transfers"] == (0, 1, 2)
    # MAVFTP: a NAK of OpenFileRO with FileNotFound, QGC's cue to use PARAM_REQUEST_LIST.
    assert got["ftp"][3] == 129
    assert got["ftp"][5] == 4
    assert got["ftp"][12] == 10
    # Not "official": QGC compares an official version with the latest stable ArduPilot.
    version = got["AUTOPILOT_VERSION"].flight_sw_version
    assert version & 0xFF != mavlink.FIRMWARE_VERSION_TYPE_OFFICIAL


async def test_the_video_stream_is_announced_by_port_at_the_rate_really_sent(
    platform_factory: Factory, tmp_path: Path, gcs: Gcs
) -> None:
    video_port = free_udp_port()
    daemon = await start(
        platform_factory,
        tmp_path,
        gcs,
        "navcam.enabled=true",
        f"navcam.port={video_port}",
        "navcam.framerate=30",
        "navcam.idle_framerate=5",
    )
    await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 100)
    since = gcs.mark()
    gcs.send(
        mavlink.MAVLink_command_long_message(
            1,
            100,
            mavlink.MAV_CMD_REQUEST_MESSAGE,
            0,
            mavlink.MAVLINK_MSG_ID_VIDEO_STREAM_INFORMATION,
            0,
            0,
            0,
            0,
            0,
            0,
        )
    )
    stream = await gcs.expect("VIDEO_STREAM_INFORMATION", since=since)
    assert stream.uri == str(video_port)  # RTP over UDP: the port alone
    # No manual override engaged: the NavCam sends its idle rate, not the configured 30.
    assert daemon.ctx.media.nav_camera()["framerate"] == 5
    assert stream.framerate == 5


def rc_override(steering_us: int, throttle_us: int) -> Any:
    return mavlink.MAVLink_rc_channels_override_message(
        1, 1, steering_us, 0, throttle_us, 0, 0, 0, 0, 0
    )


async def test_rc_overrides_drive_like_the_joystick_through_the_deadman(
    platform_factory: Factory, tmp_path: Path, gcs: Gcs
) -> None:
    """MAVProxy's ``rc 3 1750`` (RC_CHANNELS_OVERRIDE): moves nothing before MANUAL, drives in
    MANUAL (throttle channel 3, steering channel 1 to the right), and stops when it stops."""
    daemon = await start(platform_factory, tmp_path, gcs, "mavlink.allow_unsigned_control=true")
    commands: list[Velocity] = []
    daemon.bus.subscribe(topics.MOTOR_COMMAND, commands.append)
    gcs.send(rc_override(1500, 1750))
    since = gcs.mark()
    gcs.send(
        mavlink.MAVLink_command_long_message(
            1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 0, 0, 0, 0, 0, 0
        )
    )
    ack = await gcs.expect("COMMAND_ACK", since=since)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert not any(c.linear for c in commands)
    trips = daemon.ctx.telemetry.counters["arbiter"]()["deadman_trips"]
    for _ in range(5):
        gcs.send(rc_override(1375, 1750))  # half ahead, a quarter to the left
        await asyncio.sleep(0.05)
    await wait_until(lambda: Velocity(0.5, 0.25) in commands)
    moving = commands.index(Velocity(0.5, 0.25))
    await wait_until(lambda: Velocity(0.0, 0.0) in commands[moving:])
    assert daemon.ctx.telemetry.counters["arbiter"]()["deadman_trips"] > trips


async def test_guided_goes_to_a_point_around_the_keepout_and_rtl_comes_home(
    platform_factory: Factory, tmp_path: Path, gcs: Gcs
) -> None:
    """QGroundControl's "Go to location" (DO_REPOSITION): GUIDED, planned around the shed
    (the straight line crosses it), stopped there; RTL drives home the same way; AUTO goes back
    to the patrol's own route, which was kept."""
    from shapely import LineString

    daemon = await start(
        platform_factory,
        tmp_path,
        gcs,
        "mavlink.allow_unsigned_control=true",
        "mavlink.status_hz=5",  # HOME_POSITION each second, not each 5 s
        *FAST_ROVER,
    )
    patrol = daemon.ctx.patrol
    assert patrol is not None
    await wait_until(lambda: patrol.core.area is not None and patrol.core.route.waypoints)
    route = patrol.core.route
    await gcs.expect("HOME_POSITION", timeout=15)
    # QGroundControl's "Ready To Fly" first: a go-to arms through the pre-arm checks (the
    # simulated controller answering), and a loaded machine may take seconds to pass them.
    await until_armable(daemon.ctx)
    goal = at(30, 25)  # the straight line from the start crosses the shed (east 15-25, north 10-20)
    since = gcs.mark()
    gcs.send(
        mavlink.MAVLink_command_int_message(
            1,
            1,
            mavlink.MAV_FRAME_GLOBAL_INT,
            mavlink.MAV_CMD_DO_REPOSITION,
            0,
            0,
            -1,
            0,
            0,
            float("nan"),
            round(goal[0] * 1e7),
            round(goal[1] * 1e7),
            0,
        )
    )
    ack = await gcs.expect(
        "COMMAND_ACK", lambda m: m.command == mavlink.MAV_CMD_DO_REPOSITION, since=since
    )
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 1 and m.custom_mode == 15)
    area = patrol.core.area
    assert area is not None
    shed = area.keepouts["shed"]

    def planned() -> tuple[tuple[float, float], ...]:
        return patrol.core.planned_path

    await wait_until(lambda: len(planned()) >= 3, 20)  # around, not straight through
    assert not LineString(planned()).intersects(shed)
    await wait_until(lambda: patrol.core.reason.startswith("mission complete"), 90)
    pose = daemon.bus.last(topics.POSE)
    assert pose is not None
    assert math.dist(area.local(pose.latitude, pose.longitude), area.local(*goal)) < 2.0
    await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 1 and m.custom_mode == 15)

    since = gcs.mark()
    gcs.send(
        mavlink.MAVLink_command_long_message(
            1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 11, 0, 0, 0, 0, 0
        )
    )
    ack = await gcs.expect("COMMAND_ACK", since=since)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 1 and m.custom_mode == 11)
    assert patrol.detour == "home"
    (home,) = patrol.core.route.waypoints
    assert home.name == "home"

    since = gcs.mark()
    gcs.send(
        mavlink.MAVLink_command_long_message(
            1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 10, 0, 0, 0, 0, 0
        )
    )
    ack = await gcs.expect("COMMAND_ACK", since=since)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert patrol.core.route == route
    assert patrol.detour is None
