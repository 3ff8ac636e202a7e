"""A captured signed MAVLink session, sent again later, never commands the robot (issue 26,
defect 1): replay state is the vehicle's (per stream, not per UDP address), a new stream must be
within a minute of the vehicle's signing clock, and both survive a restart.

The vehicle is sans-IO: the capture is the frames a signed ground station sent; the wall
clock is injected and stepped; a restart is a new vehicle given the saved state."""

from __future__ import annotations

import hashlib
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from platformd.mavlink.signing import (
    NEW_STREAM_SLACK,
    SavedState,
    load_state,
    save_state,
    timestamp_at,
)
from platformd.mavlink.signing_state import gps_timestamp
from platformd.mavlink.vehicle import MavlinkVehicle, Request

KEY = hashlib.sha256(b"correct horse").digest()
GCS = ("192.0.2.10", 14550)
T0 = 1_790_000_000.0
"""The capture's wall-clock time (2026)."""


class Wall:
    """The platform's wall clock, stepped by the test."""

    def __init__(self, now: float) -> None:
        self.now = now

    def __call__(self) -> float:
        return self.now


class SignedStation:
    """A signed ground station (pymavlink) whose timestamps start at a given wall time."""

    def __init__(self, at: float, link_id: int = 1, system: int = 255) -> None:
        self.mav = mavlink.MAVLink(None, system, 190)
        self.mav.signing.secret_key = KEY
        self.mav.signing.sign_outgoing = True
        self.mav.signing.link_id = link_id
        self.mav.signing.timestamp = timestamp_at(at)

    def frame(self, message: Any) -> bytes:
        data = bytes(message.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        return data


def drive_session(station: SignedStation) -> list[bytes]:
    """MANUAL, the joystick forward, HOLD: what a listener on the mesh records."""
    manual = mavlink.MAVLink_command_long_message(
        1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 0, 0, 0, 0, 0, 0
    )
    joystick = mavlink.MAVLink_manual_control_message(1, 500, 0, 500, 0, 0)
    hold = mavlink.MAVLink_command_long_message(
        1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0
    )
    return [station.frame(m) for m in (manual, joystick, joystick, joystick, hold)]


def replay(
    vehicle: MavlinkVehicle, capture: list[bytes], peer: tuple[str, int], now: float
) -> list[Request]:
    requests: list[Request] = []
    for frame in capture:
        requests.extend(vehicle.feed(frame, peer, now))
    return requests


def captured(wall: Wall) -> tuple[MavlinkVehicle, list[bytes]]:
    vehicle = MavlinkVehicle(1, key=KEY, wall_clock=wall, link_timeout=10.0)
    capture = drive_session(SignedStation(wall.now))
    assert len(replay(vehicle, capture, GCS, 0.0)) == len(capture)  # the real session drives
    return vehicle, capture


def test_a_capture_from_a_new_source_port_a_second_later_is_refused() -> None:
    wall = Wall(T0)
    vehicle, capture = captured(wall)
    wall.now += 1.0
    assert replay(vehicle, capture, ("192.0.2.66", 40001), 1.0) == []
    # The real station's own address, after the vehicle forgot its link: refused as well.
    vehicle.tick(30.0)
    assert GCS not in vehicle.links
    assert replay(vehicle, capture, GCS, 30.0) == []
    assert vehicle.counters["replayed"] == 2 * len(capture)


def test_a_capture_a_minute_later_is_refused_even_once_its_streams_are_forgotten() -> None:
    wall = Wall(T0)
    vehicle, capture = captured(wall)
    wall.now += 61.0
    assert replay(vehicle, capture, ("192.0.2.66", 40002), 61.0) == []
    # A vehicle that never saw the session (its table lost): the minute window refuses it.
    fresh = MavlinkVehicle(1, key=KEY, wall_clock=wall)
    assert replay(fresh, capture, ("192.0.2.66", 40003), 0.0) == []
    assert fresh.counters["replayed"] == len(capture)
    # A stream that is new but current is taken: the window is a minute, not "never".
    station = SignedStation(wall.now - 30.0, link_id=7)
    assert len(replay(fresh, drive_session(station), ("192.0.2.11", 14550), 1.0)) == 5


def test_a_capture_after_a_restart_is_refused_and_the_real_station_goes_on(
    tmp_path: Path,
) -> None:
    wall = Wall(T0)
    vehicle, capture = captured(wall)
    assert vehicle.signatures is not None
    path = tmp_path / "signing.json"
    save_state(path, vehicle.signatures.state(), clean=True)

    # A restart a second later (well inside the minute): the saved table refuses the capture.
    wall.now += 1.0
    restarted = MavlinkVehicle(1, key=KEY, wall_clock=wall)
    saved = load_state(path)
    assert saved is not None
    assert saved.clean
    assert restarted.signatures is not None
    restarted.signatures.restore(saved)
    assert replay(restarted, capture, ("192.0.2.66", 40004), 0.0) == []
    # A restart 32 minutes later with the clock at 1970 (no RTC): the saved clock refuses it.
    wall.now = 0.0
    cold = MavlinkVehicle(1, key=KEY, wall_clock=wall)
    assert cold.signatures is not None
    cold.signatures.restore(SavedState(saved.timestamp + 32 * 60 * 100_000, {}, clean=True))
    assert replay(cold, capture, ("192.0.2.66", 40005), 0.0) == []
    # The ground station that was driving carries on with newer timestamps.
    station = SignedStation(T0 + 2.0)
    assert len(replay(restarted, drive_session(station), GCS, 1.0)) == 5


def test_after_a_crash_frames_newer_than_the_last_save_are_refused_too(tmp_path: Path) -> None:
    wall = Wall(T0)
    vehicle = MavlinkVehicle(1, key=KEY, wall_clock=wall)
    assert vehicle.signatures is not None
    station = SignedStation(T0)
    replay(vehicle, drive_session(station), GCS, 0.0)
    path = tmp_path / "signing.json"
    save_state(path, vehicle.signatures.state(), clean=False)  # a periodic save, then a crash
    capture = drive_session(station)  # sent after the save, before the crash
    assert len(replay(vehicle, capture, GCS, 1.0)) == 5
    restarted = MavlinkVehicle(1, key=KEY, wall_clock=wall)
    saved = load_state(path)
    assert saved is not None
    assert not saved.clean
    assert restarted.signatures is not None
    restarted.signatures.restore(saved)
    assert replay(restarted, capture, ("192.0.2.66", 40006), 0.0) == []


def test_the_signing_clock_never_goes_back_and_follows_gps_time() -> None:
    wall = Wall(0.0)  # no RTC, no NTP yet
    vehicle = MavlinkVehicle(1, key=KEY, wall_clock=wall)
    old = drive_session(SignedStation(T0 - 3600.0))
    vehicle.signing_clock.advance(gps_timestamp("2026-09-21T14:13:20.000Z"))
    assert vehicle.signing_clock.now() >= timestamp_at(T0) - NEW_STREAM_SLACK
    assert gps_timestamp("14:13:20.000Z") == 0  # time of day only: no date, no time
    assert replay(vehicle, old, GCS, 0.0) == []
    wall.now = T0 + 100.0
    ahead = vehicle.signing_clock.now()
    wall.now = T0  # the wall clock stepped back (NTP, an operator): the signing clock does not
    assert vehicle.signing_clock.now() == ahead


def test_a_damaged_state_file_is_an_error_not_an_empty_table(tmp_path: Path) -> None:
    path = tmp_path / "signing.json"
    assert load_state(path) is None
    path.write_text('{"timestamp": -4, "streams": []}')
    try:
        load_state(path)
    except ValueError as err:
        assert "signing state" in str(err)
    else:
        raise AssertionError("a negative timestamp was taken")
