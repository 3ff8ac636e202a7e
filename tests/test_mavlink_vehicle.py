"""The sans-IO MAVLink vehicle without sockets: frames in, frames and requests out, time given.

Lost mission items are asked for again on the vehicle's own clock; garbage is dropped and
counted; a forged signed frame with a far-future timestamp cannot lock out the real ground
station (pymavlink's own parser records a stream's timestamp before checking the signature);
mission and fence items map onto routes and keep-outs with the right refusals.
"""

from __future__ import annotations

import dataclasses
import hashlib
import math
import os
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas.messages import ControllerStatus
from platformd.mavlink.missions import (
    FENCE_EXCLUSION_CIRCLE,
    FENCE_INCLUSION_VERTEX,
    MissionItem,
    MissionRefused,
    fence_from_items,
    route_from_items,
    route_index,
)
from platformd.mavlink.model import VehicleState
from platformd.mavlink.telemetry import status_messages
from platformd.mavlink.vehicle import (
    MAX_LINKS,
    STRANGER_LINKS,
    UPLOAD_RETRIES,
    UPLOAD_RETRY_S,
    ManualInput,
    MavlinkVehicle,
    SetCurrent,
    SetMode,
    UploadItems,
)

GCS = ("127.0.0.1", 14550)
KEY = hashlib.sha256(b"passphrase").digest()


class Station:
    """pymavlink's encoder and parser, as a ground station's."""

    def __init__(self, key: bytes | None = None, timestamp: int = 10**12) -> None:
        self.mav = mavlink.MAVLink(None, 255, 190)
        if key is not None:
            self.mav.signing.secret_key = key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.link_id = 3
            self.mav.signing.timestamp = timestamp
        self.parser = mavlink.MAVLink(None, 0, 0)

    def frame(self, message: Any) -> bytes:
        data = message.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        return bytes(data)

    def read(self, vehicle: MavlinkVehicle) -> list[Any]:
        out = []
        for data, peer in vehicle.take():
            assert peer == GCS
            out.extend(self.parser.parse_buffer(data) or [])
        return out


def item(seq: int, lat: float, lon: float) -> Any:
    return mavlink.MAVLink_mission_item_int_message(
        1, 1, seq, 3, 16, 0, 1, 0, 0, 0, 0, round(lat * 1e7), round(lon * 1e7), 0, 0
    )


def test_an_upload_asks_again_for_a_lost_item_then_gives_up() -> None:
    vehicle = MavlinkVehicle(1, allow_unsigned_control=True)
    station = Station()
    vehicle.feed(station.frame(mavlink.MAVLink_mission_count_message(1, 1, 3, 0)), GCS, 0.0)
    [request] = station.read(vehicle)
    assert request.get_type() == "MISSION_REQUEST_INT"
    assert request.seq == 0
    vehicle.feed(station.frame(item(0, 1.0, 2.0)), GCS, 0.1)
    assert [m.seq for m in station.read(vehicle)] == [1]
    # Item 1 is lost: asked for again once the retry time has passed, not before.
    vehicle.tick(0.1 + UPLOAD_RETRY_S / 2)
    assert not [m for m in station.read(vehicle) if m.get_type() == "MISSION_REQUEST_INT"]
    vehicle.tick(0.1 + UPLOAD_RETRY_S * 1.01)
    assert [m.seq for m in station.read(vehicle) if m.get_type() == "MISSION_REQUEST_INT"] == [1]
    vehicle.feed(station.frame(item(1, 1.0, 2.1)), GCS, 0.5)
    requests = vehicle.feed(station.frame(item(2, 1.1, 2.1)), GCS, 0.6)
    [upload] = requests
    assert isinstance(upload, UploadItems)
    assert [i.seq for i in upload.items] == [0, 1, 2]
    vehicle.answer_upload(upload, mavlink.MAV_MISSION_ACCEPTED)
    acks = [m for m in station.read(vehicle) if m.get_type() == "MISSION_ACK"]
    assert [a.type for a in acks] == [mavlink.MAV_MISSION_ACCEPTED]
    # The ACK was lost: the station repeats its last item and gets the ACK again.
    vehicle.feed(station.frame(item(2, 1.1, 2.1)), GCS, 0.7)
    assert [m.type for m in station.read(vehicle) if m.get_type() == "MISSION_ACK"] == [0]

    # A station that never sends item 0: abandoned after the retries, with a reason.
    vehicle.feed(station.frame(mavlink.MAVLink_mission_count_message(1, 1, 2, 0)), GCS, 1.0)
    now = 1.0
    for _ in range(UPLOAD_RETRIES + 1):
        now += UPLOAD_RETRY_S * 1.01
        vehicle.tick(now)
    messages = station.read(vehicle)
    acks = [m for m in messages if m.get_type() == "MISSION_ACK"]
    assert [a.type for a in acks] == [mavlink.MAV_MISSION_OPERATION_CANCELLED]
    assert any("abandoned" in m.text for m in messages if m.get_type() == "STATUSTEXT")


def test_an_upload_window_asks_ahead_and_takes_items_in_any_order() -> None:
    vehicle = MavlinkVehicle(1, allow_unsigned_control=True, upload_window=4)
    station = Station()
    vehicle.feed(station.frame(mavlink.MAVLink_mission_count_message(1, 1, 6, 0)), GCS, 0.0)
    assert [m.seq for m in station.read(vehicle)] == [0, 1, 2, 3]
    # Item 0 is lost; 2 arrives before 1: each arrival asks for the next missing one.
    vehicle.feed(station.frame(item(2, 1.0, 2.2)), GCS, 0.05)
    vehicle.feed(station.frame(item(1, 1.0, 2.1)), GCS, 0.06)
    assert [m.seq for m in station.read(vehicle)] == [4, 5]
    vehicle.feed(station.frame(item(3, 1.0, 2.3)), GCS, 0.07)
    vehicle.feed(station.frame(item(5, 1.0, 2.5)), GCS, 0.08)
    vehicle.feed(station.frame(item(4, 1.0, 2.4)), GCS, 0.09)
    assert not station.read(vehicle)
    vehicle.tick(0.0 + UPLOAD_RETRY_S * 1.01)
    requests = [m for m in station.read(vehicle) if m.get_type() == "MISSION_REQUEST_INT"]
    assert [m.seq for m in requests] == [0]
    [upload] = vehicle.feed(station.frame(item(0, 1.0, 2.0)), GCS, 0.3)
    assert isinstance(upload, UploadItems)
    assert [i.seq for i in upload.items] == [0, 1, 2, 3, 4, 5]


def test_garbage_and_strangers_cost_nothing() -> None:
    vehicle = MavlinkVehicle(1)
    for size in (0, 1, 7, 300, 2000):
        assert vehicle.feed(os.urandom(size), ("192.0.2.9", 9999), 0.0) == []
    assert vehicle.feed(b"\xfd" * 280, ("192.0.2.9", 9999), 0.0) == []
    assert ("192.0.2.9", 9999) not in vehicle.links  # no state kept for garbage
    # A command for another vehicle is not ours to answer.
    station = Station()
    frame = station.frame(mavlink.MAVLink_command_long_message(7, 1, 176, 0, 1, 4, 0, 0, 0, 0, 0))
    assert vehicle.feed(frame, GCS, 0.0) == []
    # Nor a joystick for another vehicle, nor a command to a component we do not have.
    frame = station.frame(mavlink.MAVLink_manual_control_message(7, 1000, 0, 500, 0, 0))
    assert vehicle.feed(frame, GCS, 0.0) == []
    gimbal = mavlink.MAVLink_command_long_message(1, 154, 176, 0, 1, 4, 0, 0, 0, 0, 0)
    assert vehicle.feed(station.frame(gimbal), GCS, 0.0) == []
    assert vehicle.counters["not_for_us"] == 3
    assert not vehicle.take()
    # A flood from made-up addresses: a bounded table of links, the rest dropped and counted.
    heartbeat = station.frame(mavlink.MAVLink_heartbeat_message(6, 8, 0, 0, 0, 3))
    for port in range(1000, 1100):
        vehicle.feed(heartbeat, ("192.0.2.10", port), 0.0)
    # (strangers all: their share of the table, STRANGER_LINKS of MAX_LINKS)
    assert len(vehicle.links) == STRANGER_LINKS < MAX_LINKS
    assert vehicle.counters["links_refused"] == 100 - STRANGER_LINKS + 1  # GCS's link is one


def test_control_from_an_unsigned_link_is_refused_and_the_joystick_ignored() -> None:
    # A configured target: a stranger would get no more bytes than it sends (tested below).
    vehicle = MavlinkVehicle(1, key=KEY, targets=(GCS,))
    station = Station()
    set_auto = mavlink.MAVLink_command_long_message(1, 1, 176, 0, 1, 10, 0, 0, 0, 0, 0)
    assert vehicle.feed(station.frame(set_auto), GCS, 0.0) == []
    messages = station.read(vehicle)
    assert [m.result for m in messages if m.get_type() == "COMMAND_ACK"] == [
        mavlink.MAV_RESULT_DENIED
    ]
    joystick = mavlink.MAVLink_manual_control_message(1, 1000, 0, 500, 0, 0)
    assert vehicle.feed(station.frame(joystick), GCS, 0.1) == []
    assert vehicle.counters["refused_unsigned"] == 2

    # Nobody sets the key over the air.
    setup = mavlink.MAVLink_setup_signing_message(1, 1, [7] * 32, 0)
    assert vehicle.feed(station.frame(setup), GCS, 0.15) == []
    assert vehicle.key == KEY
    assert vehicle.counters["setup_signing_refused"] == 1
    assert any("SETUP_SIGNING refused" in m.text for m in station.read(vehicle))

    signed = Station(KEY)
    [request] = vehicle.feed(signed.frame(set_auto), GCS, 0.2)
    assert isinstance(request, SetMode)
    assert request.signed
    [manual] = vehicle.feed(signed.frame(joystick), GCS, 0.3)
    assert isinstance(manual, ManualInput)
    assert manual.linear == 1.0


def test_a_forged_future_timestamp_does_not_lock_out_the_real_station() -> None:
    vehicle = MavlinkVehicle(1, key=KEY)
    set_hold = mavlink.MAVLink_command_long_message(1, 1, 176, 0, 1, 4, 0, 0, 0, 0, 0)
    forger = Station(hashlib.sha256(b"guess").digest(), timestamp=2**47)
    forger.mav.signing.link_id = 3  # the real station's stream
    assert vehicle.feed(forger.frame(set_hold), GCS, 0.0) == []
    assert vehicle.counters["bad_signature"] == 1
    real = Station(KEY)
    [request] = vehicle.feed(real.frame(set_hold), GCS, 0.1)
    assert isinstance(request, SetMode)
    # Its own frame again is a replay.
    frame = real.frame(set_hold)
    assert len(vehicle.feed(frame, GCS, 0.2)) == 1
    assert vehicle.feed(frame, GCS, 0.3) == []
    assert vehicle.counters["replayed"] == 1


def mission(*rows: tuple[int, int]) -> list[MissionItem]:
    """(command, param1) rows at seq 0.. with made-up positions: seq 0 at (1.0, 2.0) (home:
    the global frame), the others around a circle from it (any run of them makes a valid
    polygon)."""
    return [
        MissionItem(
            seq,
            0 if seq == 0 else 3,
            command,
            param1,
            x=10_000_000 + round(1000 * math.sin(seq * 0.8)),
            y=20_000_000 + round(1000 * (1 - math.cos(seq * 0.8))),
        )
        for seq, (command, param1) in enumerate(rows)
    ]


def test_mission_items_map_onto_routes() -> None:
    plan = route_from_items(mission((16, 0), (16, 0), (16, 0), (16, 0), (177, 1)))
    assert len(plan.waypoints) == 4
    assert plan.waypoints[0] == plan.waypoints[-1]
    assert plan.home == (1.0, 2.0)
    open_route = route_from_items(mission((16, 0), (16, 0), (16, 0)))
    assert len(open_route.waypoints) == 2
    with pytest.raises(MissionRefused) as refused:
        route_from_items(mission((16, 0), (16, 0), (16, 0), (177, 2)))
    assert refused.value.result == mavlink.MAV_MISSION_INVALID_PARAM1
    with pytest.raises(MissionRefused) as refused:
        route_from_items(mission((16, 0), (21, 0)))
    assert refused.value.result == mavlink.MAV_MISSION_UNSUPPORTED
    assert "NAV_LAND" in str(refused.value)
    local = [MissionItem(0, 0, 16), MissionItem(1, mavlink.MAV_FRAME_LOCAL_NED, 16)]
    with pytest.raises(MissionRefused) as refused:
        route_from_items(local)
    assert refused.value.result == mavlink.MAV_MISSION_UNSUPPORTED_FRAME
    with pytest.raises(MissionRefused) as refused:
        route_from_items([MissionItem(0, 0, 16), MissionItem(1, 3, 16, x=950_000_000)])
    assert refused.value.result == mavlink.MAV_MISSION_INVALID_PARAM5_X


def test_fence_items_map_onto_boundary_and_keepouts() -> None:
    rows = [(FENCE_INCLUSION_VERTEX, 4)] * 4 + [(FENCE_EXCLUSION_CIRCLE, 5)]
    fence = fence_from_items(mission(*rows))
    assert fence.boundary is not None
    assert len(fence.boundary) == 4
    assert len(fence.keepouts) == 1
    assert len(fence.keepouts[0]) == 32
    with pytest.raises(MissionRefused) as refused:
        fence_from_items(mission(*[(FENCE_INCLUSION_VERTEX, 4)] * 3))
    assert refused.value.result == mavlink.MAV_MISSION_INVALID_PARAM1
    # Two triangles on opposite arcs of the circle: no common area, and no one area together.
    with pytest.raises(MissionRefused, match="do not overlap"):
        fence_from_items(mission(*[(FENCE_INCLUSION_VERTEX, 3)] * 6))
    with pytest.raises(MissionRefused, match="separate areas"):
        fence_from_items(mission(*[(FENCE_INCLUSION_VERTEX, 3)] * 6), union=True)
    with pytest.raises(MissionRefused, match="inclusion circle"):
        fence_from_items(mission((5003, 10)))


def test_a_stranger_gets_no_more_bytes_than_it_sends() -> None:
    """An address neither configured nor trusted may be a spoofed victim's: whatever it asks
    (refused control, the parameter list, a download), it gets at most the bytes it sent in
    each window, and what is held back is counted. A signed station is not held back."""
    vehicle = MavlinkVehicle(1, key=KEY, targets=(GCS,))
    vehicle.state.params = [
        (f"PARAM_{i}", float(i), mavlink.MAV_PARAM_TYPE_REAL32) for i in range(60)
    ]
    stranger, victim = Station(), ("192.0.2.7", 14550)
    asks = [
        mavlink.MAVLink_command_long_message(1, 1, 176, 0, 1, 10, 0, 0, 0, 0, 0),
        mavlink.MAVLink_param_request_list_message(1, 1),
        mavlink.MAVLink_mission_request_list_message(1, 1, 0),
        mavlink.MAVLink_setup_signing_message(1, 1, [7] * 32, 0),
    ]
    sent = received = 0
    now = 0.0
    for _ in range(50):
        for ask in asks:
            frame = stranger.frame(ask)
            sent += len(frame)
            vehicle.feed(frame, victim, now)
        vehicle.tick(now)
        received += sum(len(data) for data, peer in vehicle.take() if peer == victim)
        now += 0.1  # 5 s: half a window
    assert 0 < received <= sent
    assert vehicle.counters["stranger_frames_suppressed"] > 0
    assert vehicle.counters["stranger_bytes_suppressed"] > sent - received
    # What it gets first is an answer, in whole: the COMMAND_ACK of its first request.
    vehicle.feed(stranger.frame(asks[0]), victim, now)
    answers = stranger.parser.parse_buffer(b"".join(d for d, p in vehicle.take() if p == victim))
    assert [m.get_type() for m in answers or []] == ["COMMAND_ACK"]
    # A new window gives no credit of its own: silence earns nothing.
    held = vehicle.counters["stranger_frames_suppressed"]
    vehicle.tick(now + 9.9)  # its heartbeat is due, and its window is new
    assert not [peer for _, peer in vehicle.take() if peer == victim]
    assert vehicle.counters["stranger_frames_suppressed"] > held

    # A signed station at another address is no stranger: the whole list.
    signed, station = Station(KEY), ("192.0.2.8", 14550)
    vehicle.feed(signed.frame(mavlink.MAVLink_param_request_list_message(1, 1)), station, now)
    values = [d for d, p in vehicle.take() if p == station]
    assert len(values) == 60
    assert sum(map(len, values)) > 10 * len(signed.frame(asks[1]))


def test_set_current_needs_control_like_any_change() -> None:
    vehicle = MavlinkVehicle(1, key=KEY, targets=(GCS,))
    unsigned, signed = Station(), Station(KEY)
    by_message = mavlink.MAVLink_mission_set_current_message(1, 1, 2)
    by_command = mavlink.MAVLink_command_long_message(1, 1, 224, 0, 3, 0, 0, 0, 0, 0, 0)
    assert vehicle.feed(unsigned.frame(by_message), GCS, 0.0) == []
    assert vehicle.feed(unsigned.frame(by_command), GCS, 0.0) == []
    assert vehicle.counters["refused_unsigned"] == 2
    texts = [m.text for m in unsigned.read(vehicle) if m.get_type() == "STATUSTEXT"]
    assert texts[0].startswith("set current refused: unsigned link")
    [request] = vehicle.feed(signed.frame(by_message), GCS, 0.1)
    assert isinstance(request, SetCurrent)
    assert request.seq == 2
    assert request.command is None
    vehicle.answer_set_current(request, mavlink.MAV_RESULT_ACCEPTED)
    [current] = [m for m in unsigned.read(vehicle) if m.get_type() == "MISSION_CURRENT"]
    assert current.seq == 2
    assert vehicle.state.waypoint == 1
    [request] = vehicle.feed(signed.frame(by_command), GCS, 0.2)
    assert isinstance(request, SetCurrent)
    assert (request.seq, request.command) == (3, 224)


def test_speed_return_to_launch_and_jump_counts_map_onto_the_route() -> None:
    # ArduPilot's rover missions: home, a speed change, waypoints, RETURN_TO_LAUNCH.
    plan = route_from_items(mission((16, 0), (178, 1), (16, 0), (16, 0), (20, 0)))
    assert plan.speeds[0] is None  # param2 of the helper's rows is 0: the cruise speed
    items = mission((16, 0), (16, 0), (178, 1), (16, 0), (16, 0), (20, 0))
    items[2] = dataclasses.replace(items[2], param2=1.5)
    plan = route_from_items(items)
    assert plan.home == (1.0, 2.0)
    assert plan.waypoints[-1] == plan.home
    assert len(plan.waypoints) == 4  # home appended
    assert plan.speeds == [None, 1.5, 1.5, 1.5]
    assert plan.laps == 1
    assert plan.seqs == [1, 3, 4, 5]
    # A jump to the first waypoint repeated twice: three laps.
    items = mission((16, 0), (16, 0), (16, 0), (16, 0), (177, 1))
    items[4] = dataclasses.replace(items[4], param2=2)
    looped = route_from_items(items)
    assert looped.laps == 3
    assert looped.closed
    forever = mission((16, 0), (16, 0), (16, 0), (16, 0), (177, 1))
    forever[4] = dataclasses.replace(forever[4], param2=-1)
    assert route_from_items(forever).laps is None
    # What a rover cannot do is refused by name, or skipped (named) when asked.
    with_takeoff = mission((16, 0), (22, 0), (16, 0), (16, 0))
    with pytest.raises(MissionRefused, match="NAV_TAKEOFF"):
        route_from_items(with_takeoff)
    skipped = route_from_items(with_takeoff, skip_unsupported=True)
    assert len(skipped.waypoints) == 2
    assert "item 1: MAV_CMD_NAV_TAKEOFF (22): skipped" in skipped.notes


def test_a_first_item_in_a_relative_frame_is_a_waypoint_not_home() -> None:
    """MAVSDK's mission plugin sends its first waypoint as item 0 (relative altitude)."""
    items = mission((16, 0), (16, 0), (16, 0), (16, 0))
    items[0] = dataclasses.replace(items[0], frame=mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT_INT)
    plan = route_from_items(items)
    assert len(plan.waypoints) == 4
    assert plan.home is None
    assert plan.seqs == [0, 1, 2, 3]
    assert route_index(tuple(plan.seqs), 0) == 0


def test_a_clear_is_an_empty_upload_with_the_same_refusals() -> None:
    """MISSION_CLEAR_ALL and MISSION_COUNT start an upload by one path: unsigned, both are
    refused alike; signed, a clear asks the platform's verdict on no items at once."""
    vehicle = MavlinkVehicle(1, key=KEY, targets=(GCS,))
    unsigned, signed = Station(), Station(KEY)
    clear = mavlink.MAVLink_mission_clear_all_message(1, 1, mavlink.MAV_MISSION_TYPE_FENCE)
    count = mavlink.MAVLink_mission_count_message(1, 1, 2, mavlink.MAV_MISSION_TYPE_MISSION)
    for message, what in ((clear, "clear"), (count, "upload")):
        assert vehicle.feed(unsigned.frame(message), GCS, 0.0) == []
        answers = unsigned.read(vehicle)
        acks = [m.type for m in answers if m.get_type() == "MISSION_ACK"]
        assert acks == [mavlink.MAV_MISSION_DENIED]
        assert any(
            m.get_type() == "STATUSTEXT" and m.text.startswith(f"{what} refused: unsigned")
            for m in answers
        )
    [request] = vehicle.feed(signed.frame(clear), GCS, 0.1)
    assert isinstance(request, UploadItems)
    assert request.signed
    assert (request.mission_type, request.items) == (mavlink.MAV_MISSION_TYPE_FENCE, ())
    rally = mavlink.MAVLink_mission_clear_all_message(1, 1, mavlink.MAV_MISSION_TYPE_RALLY)
    assert vehicle.feed(signed.frame(rally), GCS, 0.2) == []
    assert [m.type for m in signed.read(vehicle) if m.get_type() == "MISSION_ACK"] == [
        mavlink.MAV_MISSION_ACCEPTED
    ]


def test_a_guided_item_without_a_position_is_denied_with_the_reason() -> None:
    vehicle = MavlinkVehicle(1, allow_unsigned_control=True)
    station = Station()
    mission_frame = mavlink.MAV_FRAME_MISSION  # no latitude, longitude
    guided = mavlink.MAVLink_mission_item_int_message(
        1, 1, 0, mission_frame, 16, 2, 1, 0, 0, 0, 0, 0, 0, 0, 0
    )
    assert vehicle.feed(station.frame(guided), GCS, 0.0) == []
    answers = station.read(vehicle)
    assert [m.type for m in answers if m.get_type() == "MISSION_ACK"] == [
        mavlink.MAV_MISSION_DENIED
    ]
    assert any(
        m.get_type() == "STATUSTEXT" and m.text == "go to: no latitude, longitude in a global frame"
        for m in answers
    )


def test_a_fitted_motor_controller_is_unhealthy_until_it_has_answered() -> None:
    """SYS_STATUS's motor-outputs bit: present from the start when a controller is fitted,
    healthy only once the driver has brought it up (not absent, which reads "none fitted")."""
    bit = mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS

    def sys_status(state: VehicleState) -> tuple[bool, bool]:
        message = status_messages(state)[0]
        present = bool(message.onboard_control_sensors_present & bit)
        return present, bool(message.onboard_control_sensors_health & bit)

    assert sys_status(VehicleState()) == (False, False)  # none fitted
    state = VehicleState(motor_present=True)
    assert sys_status(state) == (True, False)  # fitted, not heard from yet
    state.controller = ControllerStatus(True)
    assert sys_status(state) == (True, True)
    state.controller = ControllerStatus(False, error="controller silent")
    assert sys_status(state) == (True, False)
