"""FENCE_OPTIONS, the parameter a ground station may set: several inclusion fences make the
area where they all overlap (ArduPilot's default) or, with bit 1, their union (a hole in the
union stays out of bounds); only that bit is taken; an unsigned link cannot set it; the saved
value survives a restart and a damaged file is reported, not taken. (MAVProxy setting it and
uploading two fences: tests/test_mavlink_mavproxy.py.)"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from shapely import Point, Polygon

from platformd.mavlink import parameters
from platformd.mavlink.missions import FENCE_INCLUSION_VERTEX, MissionItem, fence_from_items
from platformd.mavlink.parameters import (
    FENCE_OPTIONS,
    SetParameter,
    WritableParameters,
    param_request,
    refusal,
)
from platformd.mavlink.vehicle import MavlinkVehicle

GCS = ("127.0.0.1", 14550)
KEY = hashlib.sha256(b"passphrase").digest()


def squares(*boxes: tuple[float, float, float, float]) -> list[MissionItem]:
    """Inclusion polygons, one per (west, south, east, north) in millidegrees near 10 N, 20 E."""
    items = []
    for west, south, east, north in boxes:
        for lon, lat in ((west, south), (east, south), (east, north), (west, north)):
            items.append(
                MissionItem(
                    len(items),
                    0,
                    FENCE_INCLUSION_VERTEX,
                    4,
                    x=round((10 + lat / 1000) * 1e7),
                    y=round((20 + lon / 1000) * 1e7),
                )
            )
    return items


def area(ring: Any) -> Polygon:
    return Polygon([(lon, lat) for lat, lon in ring])


def test_two_inclusion_fences_make_their_overlap_or_with_the_option_their_union() -> None:
    west, east = (0, 0, 4, 3), (2, 0, 6, 3)
    overlap = fence_from_items(squares(west, east))
    union = fence_from_items(squares(west, east), union=True)
    assert overlap.boundary is not None
    assert union.boundary is not None
    assert area(overlap.boundary).bounds == pytest.approx((20.002, 10.0, 20.004, 10.003))
    assert area(union.boundary).bounds == pytest.approx((20.0, 10.0, 20.006, 10.003))
    # Four strips round a yard: the union is a frame, the yard inside stays out of bounds.
    frame = fence_from_items(
        squares((0, 0, 6, 1), (5, 0, 6, 6), (0, 5, 6, 6), (0, 0, 1, 6)), union=True
    )
    assert frame.boundary is not None
    assert len(frame.keepouts) == 1
    assert area(frame.keepouts[0]).contains(Point(20.003, 10.003))


def test_only_bit_1_is_taken() -> None:
    assert refusal(FENCE_OPTIONS, 2.0) is None
    assert refusal(FENCE_OPTIONS, 0.0) is None
    assert "only bit 1" in (refusal(FENCE_OPTIONS, 1.0) or "")
    assert "only bit 1" in (refusal(FENCE_OPTIONS, 6.0) or "")
    assert "whole number" in (refusal(FENCE_OPTIONS, 2.5) or "")
    assert "whole number" in (refusal(FENCE_OPTIONS, float("nan")) or "")


def test_the_value_survives_a_restart_and_a_damaged_file_is_not_taken(tmp_path: Path) -> None:
    path = tmp_path / "params.json"
    kept = WritableParameters(path)
    kept.values[FENCE_OPTIONS] = 2.0
    kept.save()
    restarted = WritableParameters(path)
    restarted.load()
    assert restarted.fence_union
    assert restarted.listing() == [(FENCE_OPTIONS, 2.0, mavlink.MAV_PARAM_TYPE_INT16)]
    for damaged in ('{"FENCE_OPTIONS": 5}', '{"FENCE_OPTIONS": "2"}', "[2]", "not json"):
        path.write_text(damaged)
        with pytest.raises(ValueError, match="params.json"):
            WritableParameters(path).load()
    assert not WritableParameters(tmp_path / "absent.json").fence_union


def parameter_vehicle(**options: Any) -> tuple[MavlinkVehicle, Any, Any]:
    vehicle = MavlinkVehicle(1, **options)
    vehicle.param_request = param_request
    vehicle.state.params = [("MOTOR_BAUD", 9600.0, 6), (FENCE_OPTIONS, 0.0, 4)]
    station = mavlink.MAVLink(None, 255, 190)
    parser = mavlink.MAVLink(None, 0, 0)
    return vehicle, station, parser


def test_pymavlink_param_set_from_a_trusted_link_asks_the_platform() -> None:
    vehicle, station, parser = parameter_vehicle(allow_unsigned_control=True)
    frame = mavlink.MAVLink_param_set_message(1, 1, b"FENCE_OPTIONS", 2.0, 4).pack(station)
    [request] = vehicle.feed(bytes(frame), GCS, 0.0)
    assert isinstance(request, SetParameter)
    assert request.value == 2.0
    # Not writable: answered at once with its unchanged value.
    frame = mavlink.MAVLink_param_set_message(1, 1, b"MOTOR_BAUD", 1.0, 6).pack(station)
    assert vehicle.feed(bytes(frame), GCS, 0.0) == []
    out = [m for data, _ in vehicle.take() for m in parser.parse_buffer(data) or []]
    assert [(m.param_id, m.param_value) for m in out if m.get_type() == "PARAM_VALUE"] == [
        ("MOTOR_BAUD", 9600.0)
    ]


def test_an_unsigned_link_cannot_set_fence_options() -> None:
    vehicle, station, parser = parameter_vehicle(key=KEY, targets=(GCS,))
    frame = mavlink.MAVLink_param_set_message(1, 1, b"FENCE_OPTIONS", 2.0, 4).pack(station)
    assert vehicle.feed(bytes(frame), GCS, 0.0) == []
    out = [m for data, _ in vehicle.take() for m in parser.parse_buffer(data) or []]
    values = [(m.param_id, m.param_value) for m in out if m.get_type() == "PARAM_VALUE"]
    texts = [m.text for m in out if m.get_type() == "STATUSTEXT"]
    assert values == [(FENCE_OPTIONS, 0.0)]
    assert any("PARAM_SET FENCE_OPTIONS refused: unsigned link" in text for text in texts)


class Endpoint:
    """The service's side: authority always grants; a state dir that may not be writable."""

    def __init__(self, path: Path, vehicle: MavlinkVehicle) -> None:
        self.vehicle = vehicle
        self.parameters = WritableParameters(path)

    def refused(self, request: Any, what: str) -> str | None:
        return None


async def test_a_value_that_cannot_be_saved_is_not_set(tmp_path: Path) -> None:
    vehicle, station, parser = parameter_vehicle(allow_unsigned_control=True)
    blocked = tmp_path / "file"
    blocked.write_text("")
    endpoint = Endpoint(blocked / "params.json", vehicle)  # under a file: cannot be written
    frame = mavlink.MAVLink_param_set_message(1, 1, b"FENCE_OPTIONS", 2.0, 4).pack(station)
    [request] = vehicle.feed(bytes(frame), GCS, 0.0)
    await parameters.decide(endpoint, request)
    assert not endpoint.parameters.fence_union
    out = [m for data, _ in vehicle.take() for m in parser.parse_buffer(data) or []]
    assert [m.param_value for m in out if m.get_type() == "PARAM_VALUE"] == [0.0]
    assert any("cannot save" in m.text for m in out if m.get_type() == "STATUSTEXT")

    endpoint = Endpoint(tmp_path / "params.json", vehicle)
    await parameters.decide(endpoint, request)
    assert json.loads((tmp_path / "params.json").read_text()) == {FENCE_OPTIONS: 2}
    assert (FENCE_OPTIONS, 2.0, 4) in vehicle.state.params
