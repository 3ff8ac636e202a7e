"""The vehicle's mode numbers are ArduRover's, as pymavlink (and so MAVProxy) names them."""

from __future__ import annotations

from pymavlink import mavutil

from platformd.mavlink.modes import FlightMode, mode_named


def test_every_flight_mode_is_ardurovers_number_and_name() -> None:
    rover = mavutil.mode_mapping_rover
    for mode in FlightMode:
        assert rover.get(mode.value) == mode.name, mode


def test_ardurovers_other_modes_are_not_ours() -> None:
    others = set(mavutil.mode_mapping_rover) - {mode.value for mode in FlightMode}
    assert others  # ACRO, GUIDED, RTL, ...
    assert {number: mode_named(number) for number in others} == dict.fromkeys(others)
