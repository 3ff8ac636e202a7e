"""The MAVLink endpoint on a --sim platform, from a pymavlink ground station over loopback UDP:
identity, telemetry, parameters, MAVFTP's NAK, missions and fences both ways, modes, command
authority, signing and the joystick's deadman."""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import os
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from conftest import free_udp_port, udp_port_bound, wait_until
from mavlink_gcs import LAT, LON, Gcs, at, fence_item, sim_rover_config, waypoint
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas import topics
from brasidas.codecs.commands import MANUAL_OVERRIDE
from brasidas.media.video import PAYLOAD_TYPE
from brasidas.messages import FailsafeStep, PatrolState, Velocity
from platformd.app import PlatformDaemon
from platformd.mavlink.missions import (
    FENCE_EXCLUSION_CIRCLE,
    FENCE_EXCLUSION_VERTEX,
    FENCE_INCLUSION_VERTEX,
)
from platformd.mavlink.signing import SigningKeyError, load_signing_key
from platformd.session_table import Session

PASSPHRASE = "correct horse battery staple"


def config_for(tmp_path: Path, gcs: Gcs, *overrides: str) -> Any:
    return sim_rover_config(
        tmp_path, gcs.port, "gps.sim_rate_hz=10", "mavlink.position_hz=10", *overrides
    )


@pytest.fixture
async def gcs() -> AsyncIterator[Gcs]:
    station = await Gcs.open()
    yield station
    station.close()


Factory = Callable[..., Awaitable[PlatformDaemon]]


async def connected(
    platform_factory: Factory, tmp_path: Path, gcs: Gcs, *overrides: str
) -> PlatformDaemon:
    daemon = await platform_factory(config_for(tmp_path, gcs, *overrides), None)
    await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 1)
    arming = daemon.ctx.arming
    assert arming is not None  # AUTO arms through the pre-arm checks (a fix, the controller)
    await wait_until(lambda: not arming.reasons(), 20)
    gcs.send(
        mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3
        )
    )
    return daemon


async def test_a_ground_station_sees_a_rover_with_telemetry(
    platform_factory: Factory, tmp_path: Path, gcs: Gcs
) -> None:
    await connected(platform_factory, tmp_path, gcs, "mavlink.allow_unsigned_control=true")
    heartbeat = await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 1)
    assert heartbeat.type == mavlink.MAV_TYPE_GROUND_ROVER
    assert heartbeat.autopilot == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA
    assert heartbeat.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    assert heartbeat.custom_mode == 4  # HOLD: the demo route never starts itself
    assert heartbeat.get_srcSystem() == 1
    position = await gcs.expect("GLOBAL_POSITION_INT")
    assert abs(position.lat / 1e7 - LAT) < 1e-3
    assert abs(position.lon / 1e7 - LON) < 1e-3
    gps = await gcs.expect("GPS_RAW_INT", lambda m: m.fix_type >= 3)
    assert gps.satellites_visible > 0
    assert gps.eph < 65535
    await gcs.expect("ATTITUDE")
    await gcs.expect("VFR_HUD")
    status = await gcs.expect("SYS_STATUS", lambda m: m.voltage_battery != 65535)
    assert status.onboard_control_sensors_present & mavlink.MAV_SYS_STATUS_SENSOR_GPS
    assert status.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    await gcs.expect("BATTERY_STATUS")
    await gcs.expect("HOME_POSITION", timeout=15)

    since = gcs.mark()
    ack = await gcs.command(
        mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION
    )
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    version = await gcs.expect("AUTOPILOT_VERSION", since=since)
    for bit in ("MISSION_INT", "COMMAND_INT", "MISSION_FENCE", "MAVLINK2"):
        assert version.capabilities & getattr(mavlink, f"MAV_PROTOCOL_CAPABILITY_{bit}"), bit
    assert not version.capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_FTP

    since = gcs.mark()
    unsupported = await gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF)
    assert unsupported.result == mavlink.MAV_RESULT_UNSUPPORTED
    await gcs.expect("STATUSTEXT", lambda m: "NAV_TAKEOFF" in m.text, since=since)


async def test_parameters_are_listed_read_only_and_ftp_is_refused_cleanly(
    platform_factory: Factory, tmp_path: Path, gcs: Gcs
) -> None:
    daemon = await connected(platform_factory, tmp_path, gcs)
    since = gcs.mark()
    gcs.send(mavlink.MAVLink_param_request_list_message(1, 1))
    first = await gcs.expect("PARAM_VALUE", since=since)
    count = first.param_count
    await wait_until(
        lambda: len([m for m in gcs.received[since:] if m.get_type() == "PARAM_VALUE"]) >= count
    )
    values = {
        m.param_id: m.param_value for m in gcs.received[since:] if m.get_type() == "PARAM_VALUE"
    }
    assert len(values) == count > 20
    assert values["MAVL_SYSTEM_ID"] == 1  # mavlink.system_id, shortened to 16 characters
    assert values["PLAT_MAX_SPEED_K"] == daemon.config.platform.max_speed_kmh

    since = gcs.mark()
    gcs.send(mavlink.MAVLink_param_request_read_message(1, 1, b"MAVL_SYSTEM_ID", -1))
    by_name = await gcs.expect("PARAM_VALUE", since=since)
    assert by_name.param_id == "MAVL_SYSTEM_ID"
    assert by_name.param_value == 1
    gcs.send(mavlink.MAVLink_param_request_read_message(1, 1, b"", by_name.param_index))
    by_index = await gcs.expect("PARAM_VALUE", lambda m: m is not by_name, since=since)
    assert by_index.param_id == "MAVL_SYSTEM_ID"

    since = gcs.mark()
    gcs.send(mavlink.MAVLink_param_set_message(1, 1, b"MAVL_SYSTEM_ID", 7, 6))
    unchanged = await gcs.expect("PARAM_VALUE", since=since)
    assert unchanged.param_id == "MAVL_SYSTEM_ID"
    assert unchanged.param_value == 1
    await gcs.expect("STATUSTEXT", lambda m: "read-only" in m.text, since=since)

    since = gcs.mark()
    request = bytearray(251)
    request[0:2] = (41).to_bytes(2, "little")
    request[3] = 4  # OpenFileRO
    gcs.send(mavlink.MAVLink_file_transfer_protocol_message(0, 1, 1, list(request)))
    nak = await gcs.expect("FILE_TRANSFER_PROTOCOL", since=since)
    payload = bytes(nak.payload)
    assert int.from_bytes(payload[0:2], "little") == 42
    assert payload[3] == 129
    assert payload[5] == 4
    assert payload[12] == 10  # FileNotFound


async def test_a_mission_becomes_the_route_and_downloads_back(
    platform_factory: Factory, tmp_path: Path, gcs: Gcs
) -> None:
    daemon = await connected(platform_factory, tmp_path, gcs, "mavlink.allow_unsigned_control=true")
    corners = [at(0, 0), at(40, 0), at(40, 30), at(0, 30)]
    home = waypoint(0, *at(0, 0))
    home.frame = mavlink.MAV_FRAME_GLOBAL  # home as ArduPilot's ground stations send it
    items = [home, *(waypoint(i + 1, *p) for i, p in enumerate(corners))]
    items.append(
        mavlink.MAVLink_mission_item_int_message(
            1, 1, 5, 2, mavlink.MAV_CMD_DO_JUMP, 0, 1, 1, -1, 0, 0, 0, 0, 0, 0
        )
    )
    ack = await gcs.upload(items)
    assert ack.type == mavlink.MAV_MISSION_ACCEPTED
    route = daemon.ctx.patrol.core.route  # type: ignore[union-attr]
    assert route.closed
    assert route.stops == 4
    assert (route.waypoints[1].latitude, route.waypoints[1].longitude) == pytest.approx(
        corners[1], abs=1e-7
    )
    back = await gcs.download()
    assert [(m.seq, m.command, m.x, m.y) for m in back] == [
        (m.seq, m.command, m.x, m.y) for m in items
    ]

    # A waypoint in the shed: refused with the map's reason, the route unchanged.
    since = gcs.mark()
    bad = [home, waypoint(1, *at(0, 0)), waypoint(2, *at(20, 15))]
    ack = await gcs.upload(bad)
    assert ack.type == mavlink.MAV_MISSION_INVALID_PARAM5_X
    text = await gcs.expect_text(lambda t: "shed" in t, since)
    assert text.startswith(
        "mission upload refused: waypoint 2"
    )  # counted from 1, as the console, the CLI and a ground station number it
    assert daemon.ctx.patrol.core.route == route  # type: ignore[union-attr]

    # A takeoff has no place in a rover's route.
    takeoff = mavlink.MAVLink_mission_item_int_message(
        1, 1, 1, 3, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 1, 0, 0, 0, 0, 0, 0, 10, 0
    )
    ack = await gcs.upload([home, takeoff])
    assert ack.type == mavlink.MAV_MISSION_UNSUPPORTED


async def test_modes_start_and_stop_the_patrol(
    platform_factory: Factory, tmp_path: Path, gcs: Gcs
) -> None:
    daemon = await connected(platform_factory, tmp_path, gcs, "mavlink.allow_unsigned_control=true")
    ack = await gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 10)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 1 and m.custom_mode == 10)
    status = daemon.bus.last(topics.PATROL_STATUS)
    assert status is not None
    assert status.state is PatrolState.PATROLLING
    ack = await gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 4)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 1 and m.custom_mode == 4)
    ack = await gcs.command(mavlink.MAV_CMD_MISSION_START)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 1 and m.custom_mode == 10)
    ack = await gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 3)  # STEERING: not ours
    assert ack.result == mavlink.MAV_RESULT_UNSUPPORTED


async def test_a_fence_reshapes_the_map_and_downloads_back(
    platform_factory: Factory, tmp_path: Path, gcs: Gcs
) -> None:
    daemon = await connected(platform_factory, tmp_path, gcs, "mavlink.allow_unsigned_control=true")
    patrol = daemon.ctx.patrol
    assert patrol is not None
    boundary = [at(-12, -12), at(52, -12), at(52, 42), at(-12, 42)]
    tank = [at(30, 12), at(34, 12), at(34, 16)]
    items = [
        *(fence_item(i, FENCE_INCLUSION_VERTEX, 4, *p) for i, p in enumerate(boundary)),
        *(fence_item(4 + i, FENCE_EXCLUSION_VERTEX, 3, *p) for i, p in enumerate(tank)),
        fence_item(7, FENCE_EXCLUSION_CIRCLE, 3.0, *at(20, 15)),
    ]
    ack = await gcs.upload(items, mission_type=1)
    assert ack.type == mavlink.MAV_MISSION_ACCEPTED
    assert ack.mission_type == 1
    area = patrol.core.area
    assert area is not None
    assert sorted(area.keepouts) == ["fence-1", "fence-2"]
    assert area.boundary.area == pytest.approx(64 * 54, rel=0.02)
    back = await gcs.download(mission_type=1)
    assert [(m.command, m.param1, m.x, m.y) for m in back] == [
        (m.command, m.param1, m.x, m.y) for m in items
    ]

    # A keep-out on the route's first waypoint (the demo loop's south-west corner): refused.
    since = gcs.mark()
    ack = await gcs.upload([fence_item(0, FENCE_EXCLUSION_CIRCLE, 2.0, *at(0, 0))], mission_type=1)
    assert ack.type == mavlink.MAV_MISSION_INVALID_PARAM5_X
    assert "keep-out" in await gcs.expect_text(lambda t: "fence upload refused" in t, since)
    assert sorted(patrol.core.area.keepouts) == ["fence-1", "fence-2"]  # type: ignore[union-attr]


async def test_an_observer_ground_station_is_refused_with_the_holders_id(
    platform_factory: Factory, tmp_path: Path, gcs: Gcs
) -> None:
    daemon = await connected(platform_factory, tmp_path, gcs, "mavlink.allow_unsigned_control=true")
    ack = await gcs.command(mavlink.MAV_CMD_MISSION_START)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert daemon.ctx.authority.station_id == f"gcs255@127.0.0.1:{gcs.port}"

    other = await Gcs.open(system=254)
    try:
        other.vehicle = gcs.vehicle
        since = other.mark()
        ack = await other.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 10)  # AUTO: moving
        assert ack.result == mavlink.MAV_RESULT_DENIED
        assert ack.result_param2 == 255  # the holder's system id
        text = await other.expect_text(lambda t: "refused" in t, since)
        assert f"gcs255@127.0.0.1:{gcs.port}" in text
        ack = await other.upload([waypoint(0, *at(0, 0)), waypoint(1, *at(10, 0))])
        assert ack.type == mavlink.MAV_MISSION_DENIED
        # Watching stays open to it.
        assert len(await other.download()) == 6  # home and the demo loop
    finally:
        other.close()

    # A station takes control back with --force (MOVRD state=on,force=1).
    now = time.monotonic()
    station = Session("station-session", "station-1", "127.0.0.1", None, now, now)
    daemon.ctx.sessions.open(station)
    result = await daemon.ctx.commands.dispatch(MANUAL_OVERRIDE, "state=on,force=1", station)
    assert result.accepted
    ack = await gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 10)
    assert ack.result == mavlink.MAV_RESULT_DENIED
    assert ack.result_param2 == 0
    daemon.ctx.sessions.close(station.session_id, "test over")


async def test_set_current_chooses_the_patrols_next_waypoint_for_the_holder_only(
    platform_factory: Factory, tmp_path: Path, gcs: Gcs
) -> None:
    daemon = await connected(platform_factory, tmp_path, gcs, "mavlink.allow_unsigned_control=true")
    patrol = daemon.ctx.patrol
    assert patrol is not None
    assert patrol.core.route.stops == 4  # the demo loop

    def waypoint_reported() -> int | None:
        status = daemon.bus.last(topics.PATROL_STATUS)
        return status.waypoint if status is not None else None

    # MISSION_SET_CURRENT 3 (item 0 is home): the third waypoint, index 2; answered at once.
    since = gcs.mark()
    gcs.send(mavlink.MAVLink_mission_set_current_message(1, 1, 3))
    await gcs.expect("MISSION_CURRENT", lambda m: m.seq == 3, since=since)
    assert patrol.core.cursor.index == 2
    assert waypoint_reported() == 2
    # None such, or home: refused with the reason, the target unchanged.
    for seq, reason in ((9, "no waypoint 9: the route has 4"), (0, "item 0 is home")):
        since = gcs.mark()
        gcs.send(mavlink.MAVLink_mission_set_current_message(1, 1, seq))
        text = await gcs.expect_text(lambda t, r=reason: r in t, since)  # chunks joined
        assert text.startswith("set current refused: ")
    assert patrol.core.cursor.index == 2
    # By command (DO_SET_MISSION_CURRENT): a COMMAND_ACK.
    ack = await gcs.command(mavlink.MAV_CMD_DO_SET_MISSION_CURRENT, 2)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert patrol.core.cursor.index == 1
    ack = await gcs.command(mavlink.MAV_CMD_DO_SET_MISSION_CURRENT, 7)
    assert ack.result == mavlink.MAV_RESULT_FAILED

    # Another ground station while this one holds control: refused, the holder named.
    other = await Gcs.open(system=254)
    try:
        other.vehicle = gcs.vehicle
        since = other.mark()
        ack = await other.command(mavlink.MAV_CMD_DO_SET_MISSION_CURRENT, 4)
        assert ack.result == mavlink.MAV_RESULT_DENIED
        assert ack.result_param2 == 255
        since = other.mark()
        other.send(mavlink.MAVLink_mission_set_current_message(1, 1, 4))
        holder = f"gcs255@127.0.0.1:{gcs.port}"
        text = await other.expect_text(lambda t: holder in t, since)
        assert "refused" in text
    finally:
        other.close()
    assert patrol.core.cursor.index == 1

    # Started, the patrol heads for the waypoint chosen.
    ack = await gcs.command(mavlink.MAV_CMD_MISSION_START)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    status = daemon.bus.last(topics.PATROL_STATUS)
    assert status is not None
    assert status.waypoint == 1


async def test_manual_control_drives_through_the_deadman(
    platform_factory: Factory, tmp_path: Path, gcs: Gcs
) -> None:
    daemon = await connected(platform_factory, tmp_path, gcs, "mavlink.allow_unsigned_control=true")
    commands: list[Velocity] = []
    daemon.bus.subscribe(topics.MOTOR_COMMAND, commands.append)
    # The joystick before MANUAL moves nothing.
    gcs.send(mavlink.MAVLink_manual_control_message(1, 500, 0, 500, 0, 0))
    ack = await gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 0)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    assert not any(c.linear for c in commands)
    await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 1 and m.custom_mode == 0)
    trips = daemon.ctx.telemetry.counters["arbiter"]()["deadman_trips"]
    for _ in range(5):
        gcs.send(mavlink.MAVLink_manual_control_message(1, 500, 0, 500, -250, 0))
        await asyncio.sleep(0.05)
    await wait_until(lambda: Velocity(0.5, 0.25) in commands)
    moving = commands.index(Velocity(0.5, 0.25))
    # It stops arriving: the arbiter's deadman stops the robot.
    await wait_until(lambda: Velocity(0.0, 0.0) in commands[moving:])
    assert daemon.ctx.telemetry.counters["arbiter"]()["deadman_trips"] > trips
    motion = daemon.bus.last(topics.MOTION_STATE)
    assert motion is not None
    assert motion.deadman


async def test_signing_control_needs_a_signed_link_and_replays_are_refused(
    platform_factory: Factory, tmp_path: Path, gcs: Gcs
) -> None:
    key_file = tmp_path / "mavlink.pass"
    key_file.write_text(PASSPHRASE + "\n")
    key_file.chmod(0o600)
    daemon = await connected(
        platform_factory, tmp_path, gcs, f"mavlink.signing_key_file={key_file}"
    )
    heartbeat = await gcs.expect("HEARTBEAT")
    assert heartbeat.get_msgbuf()[2] & 0x01  # the vehicle signs what it sends
    counters = daemon.ctx.telemetry.counters["mavlink"]

    # Unsigned: watching and downloading, yes; changing the robot, no.
    assert len(await gcs.download()) == 6
    since = gcs.mark()
    ack = await gcs.command(mavlink.MAV_CMD_MISSION_START)
    assert ack.result == mavlink.MAV_RESULT_DENIED
    await gcs.expect_text(lambda t: "unsigned" in t, since)
    ack = await gcs.upload([waypoint(0, *at(0, 0)), waypoint(1, *at(10, 0))])
    assert ack.type == mavlink.MAV_MISSION_DENIED

    # A wrong passphrase is dropped and counted.
    gcs.sign("wrong")
    bad = counters().get("bad_signature", 0)
    gcs.send(mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_MISSION_START, 0, *[0] * 7))
    await wait_until(lambda: counters().get("bad_signature", 0) > bad)

    gcs.sign(PASSPHRASE)
    ack = await gcs.command(mavlink.MAV_CMD_MISSION_START)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    ack = await gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 4)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    # The same signed frame again: refused and counted, the mode stays HOLD.
    replayed = counters().get("replayed", 0)
    since = gcs.mark()
    gcs.send_raw(gcs.frames[-2])  # the signed MISSION_START
    await wait_until(lambda: counters().get("replayed", 0) > replayed)
    status = daemon.bus.last(topics.PATROL_STATUS)
    assert status is not None
    assert status.state is not PatrolState.PATROLLING
    assert not [m for m in gcs.received[since:] if m.get_type() == "COMMAND_ACK"]


async def test_a_stranger_gets_no_more_bytes_than_it_sends(
    platform_factory: Factory, tmp_path: Path, gcs: Gcs
) -> None:
    """An unsigned address not in mavlink.targets may be a spoofed one: a burst of refused
    commands and parameter lists from it gets back no more bytes than it sent."""
    key_file = tmp_path / "mavlink.pass"
    key_file.write_text(PASSPHRASE + "\n")
    key_file.chmod(0o600)
    daemon = await connected(
        platform_factory, tmp_path, gcs, f"mavlink.signing_key_file={key_file}"
    )
    counters = daemon.ctx.telemetry.counters["mavlink"]
    stranger = await Gcs.open(system=254)
    try:
        stranger.vehicle = gcs.vehicle
        start = mavlink.MAVLink_command_long_message(
            1, 1, mavlink.MAV_CMD_MISSION_START, 0, *[0] * 7
        )
        for n in range(60):
            stranger.send(start if n % 6 else mavlink.MAVLink_param_request_list_message(1, 1))
        sent = sum(len(frame) for frame in stranger.frames)
        await wait_until(lambda: counters().get("refused_unsigned", 0) >= 50)
        # Two heartbeats later every answer has arrived, and the telemetry of those ticks
        # (broadcast to whoever was heard: the stranger's share is held back too).
        for _ in range(2):
            await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 1)
        assert 0 < stranger.bytes_received <= sent
        denied = [m for m in stranger.received if m.get_type() == "COMMAND_ACK"]
        assert denied
        assert all(m.result == mavlink.MAV_RESULT_DENIED for m in denied)
        assert counters().get("stranger_bytes_suppressed", 0) > sent - stranger.bytes_received
    finally:
        stranger.close()
    # The configured ground station is not held back.
    assert len(await gcs.download()) == 6


def test_the_signing_passphrase_file_must_be_owner_only(tmp_path: Path) -> None:
    key_file = tmp_path / "mavlink.pass"
    key_file.write_text(PASSPHRASE + "\n")
    key_file.chmod(0o644)
    # The fleet key's rule and words (brasidas.security.read_private_file), the fix named.
    with pytest.raises(SigningKeyError) as refused:
        load_signing_key(key_file)
    assert str(refused.value) == (
        f"{key_file}: permissions 0644 for the MAVLink signing key are too open: it must be "
        f"accessible by its owner only (chmod 600 {key_file})"
    )
    key_file.chmod(0o620)  # writable by the group: as bad
    with pytest.raises(SigningKeyError, match=f"too open: .*chmod 600 {key_file}"):
        load_signing_key(key_file)
    key_file.chmod(0o600)
    assert load_signing_key(key_file) == hashlib.sha256(PASSPHRASE.encode()).digest()
    key_file.write_text("")
    with pytest.raises(SigningKeyError, match="one non-empty line"):
        load_signing_key(key_file)


async def test_a_signing_key_that_is_a_fifo_or_huge_is_refused_at_once(tmp_path: Path) -> None:
    fifo = tmp_path / "mavlink.fifo"
    os.mkfifo(fifo, 0o600)
    loading = asyncio.create_task(asyncio.to_thread(load_signing_key, fifo))
    try:
        # Opening a FIFO with no writer waits for one forever: the start would hang.
        with pytest.raises(SigningKeyError, match="not a regular file"):
            await asyncio.wait_for(asyncio.shield(loading), 10.0)
    finally:
        if not loading.done():  # the old reader: give it a writer and an end so it returns
            with contextlib.suppress(OSError):
                os.close(os.open(fifo, os.O_WRONLY | os.O_NONBLOCK))
            with contextlib.suppress(Exception):
                await loading
    huge = tmp_path / "mavlink.pass"
    huge.write_bytes(b"x" * 1_000_000)
    huge.chmod(0o600)
    with pytest.raises(SigningKeyError, match="more than the 4096 allowed"):
        load_signing_key(huge)


async def test_the_navcam_announced_to_a_ground_station_decodes_with_gstreamer(
    platform_factory: Factory, tmp_path: Path, gcs: Gcs
) -> None:
    video_port = free_udp_port()
    await connected(
        platform_factory, tmp_path, gcs, "navcam.enabled=true", f"navcam.port={video_port}"
    )
    await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 100)
    since = gcs.mark()
    ack = await gcs.command(
        mavlink.MAV_CMD_REQUEST_MESSAGE,
        mavlink.MAVLINK_MSG_ID_CAMERA_INFORMATION,
        component=100,
    )
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    info = await gcs.expect("CAMERA_INFORMATION", since=since)
    assert info.flags & mavlink.CAMERA_CAP_FLAGS_HAS_VIDEO_STREAM
    # QGroundControl's stock receiver: RTP/H.264 on the announced UDP port.
    receiver = await asyncio.create_subprocess_exec(
        "gst-launch-1.0",
        "-q",
        "udpsrc",
        f"port={video_port}",
        "address=127.0.0.1",
        f"caps=application/x-rtp,media=video,encoding-name=H264,clock-rate=90000,payload={PAYLOAD_TYPE}",
        "!",
        "rtph264depay",
        "!",
        "h264parse",
        "!",
        "avdec_h264",
        "!",
        "fakesink",
        "num-buffers=5",
        stdout=asyncio.subprocess.DEVNULL,
        stderr=asyncio.subprocess.PIPE,
    )
    try:
        await wait_until(lambda: udp_port_bound(video_port))
        since = gcs.mark()
        ack = await gcs.command(
            mavlink.MAV_CMD_REQUEST_MESSAGE,
            mavlink.MAVLINK_MSG_ID_VIDEO_STREAM_INFORMATION,
            component=100,
        )
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED
        stream = await gcs.expect("VIDEO_STREAM_INFORMATION", since=since)
        assert stream.type == mavlink.VIDEO_STREAM_TYPE_RTPUDP
        assert stream.uri == str(video_port)
        assert stream.get_srcComponent() == 100
        assert await asyncio.wait_for(receiver.wait(), 60) == 0  # five decoded frames
    finally:
        if receiver.returncode is None:
            receiver.kill()
            await receiver.wait()


async def test_a_silent_ground_station_in_manual_trips_the_failsafe_ladder(
    platform_factory: Factory, tmp_path: Path, gcs: Gcs
) -> None:
    daemon = await connected(platform_factory, tmp_path, gcs, "mavlink.allow_unsigned_control=true")
    ack = await gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 0)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    since = gcs.mark()
    # The station goes quiet (no heartbeat, no joystick): the ladder holds, and the group 90
    # warning reaches the ground station as a CRITICAL STATUSTEXT.
    text = await gcs.expect_text(lambda t: t.startswith("90.18 LINK LOST"), since, timeout=20)
    assert "hold" in text
    failsafe = daemon.bus.last(topics.FAILSAFE_STATE)
    assert failsafe is not None
    assert failsafe.step is FailsafeStep.HOLD
    severities = {
        m.severity
        for m in gcs.received[since:]
        if m.get_type() == "STATUSTEXT" and "LINK" in m.text
    }
    assert severities == {mavlink.MAV_SEVERITY_CRITICAL}
    heartbeat = await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 1)
    assert heartbeat.system_status == mavlink.MAV_STATE_CRITICAL


async def test_unsigned_heartbeats_do_not_keep_a_signed_controller_alive(
    platform_factory: Factory, tmp_path: Path, gcs: Gcs
) -> None:
    key_file = tmp_path / "mavlink.pass"
    key_file.write_text(PASSPHRASE)
    key_file.chmod(0o600)
    daemon = await connected(
        platform_factory, tmp_path, gcs, f"mavlink.signing_key_file={key_file}"
    )
    gcs.sign(PASSPHRASE)
    ack = await gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 0)
    assert ack.result == mavlink.MAV_RESULT_ACCEPTED
    # Someone spoofing the station's address without the key: its heartbeats are heard
    # (watching is open) but hold off neither the ladder nor the session's end.
    gcs.mav.signing.sign_outgoing = False
    heartbeat = mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3
    )

    def held() -> bool:
        gcs.send(heartbeat)
        failsafe = daemon.bus.last(topics.FAILSAFE_STATE)
        return failsafe is not None and failsafe.step is FailsafeStep.HOLD

    await wait_until(held, timeout=20)
