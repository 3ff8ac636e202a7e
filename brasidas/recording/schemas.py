"""The recorded channels' schemas and message encoders, shared by the platform's recorder and
the station's live Foxglove server (one definition, both ends).

Messages are JSON (``message_encoding "json"``, schemas ``jsonschema``): Foxglove's well-known
schemas where one fits (``foxglove.LocationFix``, ``foxglove.PoseInFrame``,
``foxglove.CompressedVideo``, ``foxglove.Log``, ``foxglove.GeoJSON``; bytes fields base64, as
Foxglove reads them in JSON), and ``brasidas.*`` schemas for the rest, the telemetry sections'
generated from the telemetry schema's dataclasses (:mod:`brasidas.codecs.telemetry_schema`).
"""

from __future__ import annotations

import base64
import dataclasses
import math
import types
import typing
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import orjson

from brasidas.codecs.telemetry_schema import SECTIONS, Section, section_to_json
from brasidas.messages import CommandReceived

MESSAGE_ENCODING = "json"
SCHEMA_ENCODING = "jsonschema"


@dataclass(frozen=True)
class ChannelSpec:
    """One channel: its topic, its schema's name and JSON Schema."""

    topic: str
    schema_name: str
    schema: dict[str, Any]

    def schema_bytes(self) -> bytes:
        return orjson.dumps(self.schema)


_TIME = {
    "type": "object",
    "title": "time",
    "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer"}},
}


def _object(title: str, properties: dict[str, Any]) -> dict[str, Any]:
    return {"title": title, "type": "object", "properties": properties}


LOCATION_FIX = _object(
    "foxglove.LocationFix",
    {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "latitude": {"type": "number"},
        "longitude": {"type": "number"},
        "altitude": {"type": "number"},
        "position_covariance": {"type": "array", "items": {"type": "number"}},
        "position_covariance_type": {
            "type": "integer",
            "description": "0 unknown, 1 approximated, 2 diagonal known, 3 known",
        },
    },
)
_VECTOR3 = _object("foxglove.Vector3", {k: {"type": "number"} for k in "xyz"})
_QUATERNION = _object("foxglove.Quaternion", {k: {"type": "number"} for k in "xyzw"})
POSE_IN_FRAME = _object(
    "foxglove.PoseInFrame",
    {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "pose": _object("foxglove.Pose", {"position": _VECTOR3, "orientation": _QUATERNION}),
    },
)
COMPRESSED_VIDEO = _object(
    "foxglove.CompressedVideo",
    {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "data": {"type": "string", "contentEncoding": "base64"},
        "format": {"type": "string"},
    },
)
LOG = _object(
    "foxglove.Log",
    {
        "timestamp": _TIME,
        "level": {
            "type": "integer",
            "description": "1 debug, 2 info, 3 warning, 4 error, 5 fatal",
        },
        "message": {"type": "string"},
        "name": {"type": "string"},
        "file": {"type": "string"},
        "line": {"type": "integer", "minimum": 0},
    },
)
GEOJSON = _object("foxglove.GeoJSON", {"geojson": {"type": "string"}})

COMMAND = _object(
    "brasidas.Command",
    {
        "kind": {"type": "string", "description": "system (a command code) or rpc (a method)"},
        "name": {"type": "string", "description": "the code (10.4) or the method"},
        "payload": {"type": "string"},
        "station": {"type": ["string", "null"], "description": "the sending station"},
        "accepted": {"type": "boolean"},
        "reason": {"type": "string"},
    },
)
VELOCITY = _object(
    "brasidas.Velocity",
    {"linear": {"type": "number"}, "angular": {"type": "number"}},
)
STATE_CHANGE = _object(
    "brasidas.StateChange",
    {
        "what": {"type": "string", "description": "failsafe, control, override, stream, ..."},
        "state": {"type": "string"},
        "station": {"type": ["string", "null"]},
        "reason": {"type": "string"},
    },
)

LASER_SCAN = _object(
    "foxglove.LaserScan",
    {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "pose": _object("foxglove.Pose", {"position": _VECTOR3, "orientation": _QUATERNION}),
        "start_angle": {"type": "number"},
        "end_angle": {"type": "number"},
        "ranges": {"type": "array", "items": {"type": "number"}},
        "intensities": {"type": "array", "items": {"type": "number"}},
    },
)

GRID = _object(
    "foxglove.Grid",
    {
        "timestamp": _TIME,
        "frame_id": {"type": "string"},
        "pose": _object("foxglove.Pose", {"position": _VECTOR3, "orientation": _QUATERNION}),
        "column_count": {"type": "integer", "minimum": 0},
        "cell_size": _object(
            "foxglove.Vector2", {"x": {"type": "number"}, "y": {"type": "number"}}
        ),
        "row_stride": {"type": "integer", "minimum": 0},
        "cell_stride": {"type": "integer", "minimum": 0},
        "fields": {
            "type": "array",
            "items": _object(
                "foxglove.PackedElementField",
                {
                    "name": {"type": "string"},
                    "offset": {"type": "integer", "minimum": 0},
                    "type": {"type": "integer", "description": "1 UINT8"},
                },
            ),
        },
        "data": {"type": "string", "contentEncoding": "base64"},
    },
)
GRID_FRAME = "grid"
"""The frame of the occupancy grid and the fused pose: the lidar localization's (x east,
y north, metres from the grid's anchor; not ``local``, the GPS+IMU localization's)."""

LOG_DEBUG, LOG_INFO, LOG_WARNING, LOG_ERROR = 1, 2, 3, 4


def section_schema(cls: type[Section]) -> dict[str, Any]:
    """The JSON Schema of a telemetry section, from its dataclass (names, types, docs, units)."""
    hints = typing.get_type_hints(cls)
    properties: dict[str, Any] = {}
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        prop = _type_schema(hints[f.name])
        doc = " ".join(x for x in (f.metadata.get("doc", ""), f.metadata.get("unit", "")) if x)
        if doc:
            prop["description"] = doc
        properties[f.name] = prop
    return _object(f"brasidas.telemetry.{cls.__name__}", properties)


def _type_schema(tp: Any) -> dict[str, Any]:
    origin = typing.get_origin(tp)
    if origin is types.UnionType or origin is typing.Union:
        inner = [arg for arg in typing.get_args(tp) if arg is not type(None)]
        schema = _type_schema(inner[0])
        kind = schema.get("type")
        if isinstance(kind, str):
            schema["type"] = [kind, "null"]
        return schema
    simple = {bool: "boolean", int: "integer", float: "number", str: "string"}
    if tp in simple:
        return {"type": simple[tp]}
    if origin is tuple:
        return {"type": "array", "items": _type_schema(typing.get_args(tp)[0])}
    if origin is dict:
        return {"type": "object", "additionalProperties": _type_schema(typing.get_args(tp)[1])}
    if isinstance(tp, type) and issubclass(tp, Section):
        return section_schema(tp)
    return {}


# --------------------------------------------------------------------------- the channels

NAVCAM = ChannelSpec("/navcam", "foxglove.CompressedVideo", COMPRESSED_VIDEO)
GPS = ChannelSpec("/gps", "foxglove.LocationFix", LOCATION_FIX)
POSE = ChannelSpec("/pose", "foxglove.LocationFix", LOCATION_FIX)
POSE_LOCAL = ChannelSpec("/pose/local", "foxglove.PoseInFrame", POSE_IN_FRAME)
LOG_CHANNEL = ChannelSpec("/log", "foxglove.Log", LOG)
MAP = ChannelSpec("/map", "foxglove.GeoJSON", GEOJSON)
ROUTE = ChannelSpec("/route", "foxglove.GeoJSON", GEOJSON)
COMMANDS = ChannelSpec("/commands", "brasidas.Command", COMMAND)
TELEOP_VELOCITY = ChannelSpec("/velocity/teleop", "brasidas.Velocity", VELOCITY)
AUTONOMY_VELOCITY = ChannelSpec("/velocity/autonomy", "brasidas.Velocity", VELOCITY)
MOTOR_COMMAND = ChannelSpec("/motor/command", "brasidas.Velocity", VELOCITY)
STATE = ChannelSpec("/state", "brasidas.StateChange", STATE_CHANGE)
LIDAR_SCAN = ChannelSpec("/lidar/scan", "foxglove.LaserScan", LASER_SCAN)
OCCUPANCY_GRID = ChannelSpec("/grid", "foxglove.Grid", GRID)
FUSED_POSE = ChannelSpec("/pose/fused", "foxglove.LocationFix", LOCATION_FIX)
FUSED_POSE_LOCAL = ChannelSpec("/pose/fused/local", "foxglove.PoseInFrame", POSE_IN_FRAME)
TELEMETRY: dict[type[Section], ChannelSpec] = {
    cls: ChannelSpec(f"/telemetry/{cls.NAME}", f"brasidas.telemetry.{cls.__name__}", {})
    for cls in SECTIONS
}


def telemetry_channel(cls: type[Section]) -> ChannelSpec:
    """A section's channel, its schema generated on first use."""
    spec = TELEMETRY[cls]
    if not spec.schema:
        spec = TELEMETRY[cls] = ChannelSpec(spec.topic, spec.schema_name, section_schema(cls))
    return spec


def all_channels() -> list[ChannelSpec]:
    """Every channel the recorder writes, in a stable order (their ids follow it)."""
    return [
        NAVCAM,
        GPS,
        POSE,
        POSE_LOCAL,
        LOG_CHANNEL,
        STATE,
        MAP,
        ROUTE,
        COMMANDS,
        TELEOP_VELOCITY,
        AUTONOMY_VELOCITY,
        MOTOR_COMMAND,
        LIDAR_SCAN,
        OCCUPANCY_GRID,
        FUSED_POSE,
        FUSED_POSE_LOCAL,
        *(telemetry_channel(cls) for cls in SECTIONS),
    ]


# --------------------------------------------------------------------------- encoders


def stamp(time_ns: int) -> dict[str, int]:
    return {"sec": time_ns // 1_000_000_000, "nsec": time_ns % 1_000_000_000}


def encode_location(
    time_ns: int, latitude: float, longitude: float, altitude: float | None, sigma_m: float | None
) -> bytes:
    """foxglove.LocationFix; ``sigma_m`` (1 sigma, horizontal) fills a diagonal covariance."""
    variance = sigma_m * sigma_m if sigma_m is not None and math.isfinite(sigma_m) else 0.0
    return orjson.dumps(
        {
            "timestamp": stamp(time_ns),
            "frame_id": "wgs84",
            "latitude": latitude,
            "longitude": longitude,
            "altitude": altitude if altitude is not None else 0.0,
            "position_covariance": [variance, 0, 0, 0, variance, 0, 0, 0, variance * 4],
            "position_covariance_type": 2 if variance else 0,
        }
    )


def encode_pose(
    time_ns: int, x_m: float, y_m: float, yaw_rad: float, frame_id: str = "local"
) -> bytes:
    """foxglove.PoseInFrame in the localization's local frame (x east, y north, yaw about z)."""
    half = yaw_rad / 2
    return orjson.dumps(
        {
            "timestamp": stamp(time_ns),
            "frame_id": frame_id,
            "pose": {
                "position": {"x": x_m, "y": y_m, "z": 0.0},
                "orientation": {"x": 0.0, "y": 0.0, "z": math.sin(half), "w": math.cos(half)},
            },
        }
    )


def encode_laser_scan(
    time_ns: int, bearings_deg: Sequence[float], ranges_m: Sequence[float]
) -> bytes:
    """foxglove.LaserScan in the robot's frame (``base_link``: x forward, y left), one range a
    degree counter-clockwise from forward (the nearest return in it; 0: none)."""
    ranges = [0.0] * 360
    for bearing, distance in zip(bearings_deg, ranges_m, strict=True):
        if distance > 0:
            ccw = round(-bearing) % 360
            ranges[ccw] = distance if ranges[ccw] == 0 else min(ranges[ccw], distance)
    return _laser_scan(time_ns, ranges, math.radians(359.0))


def encode_sector_scan(time_ns: int, ranges_dm: Sequence[int]) -> bytes:
    """foxglove.LaserScan from the telemetry's sectors (:mod:`brasidas.perception.view`: the
    nearest return of each sector clockwise from forward, dm): the same channel as the
    recorder's full scan, one range a sector counter-clockwise from forward."""
    count = len(ranges_dm)
    ranges = [ranges_dm[(count - k) % count] / 10 for k in range(count)] if count else []
    return _laser_scan(time_ns, ranges, 2 * math.pi * (count - 1) / count if count else 0.0)


def _laser_scan(time_ns: int, ranges: list[float], end_angle: float) -> bytes:
    """foxglove.LaserScan in ``base_link``, ``ranges`` evenly counter-clockwise from forward
    to ``end_angle`` (radians)."""
    return orjson.dumps(
        {
            "timestamp": stamp(time_ns),
            "frame_id": "base_link",
            "pose": {
                "position": {"x": 0.0, "y": 0.0, "z": 0.0},
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
            },
            "start_angle": 0.0,
            "end_angle": end_angle,
            "ranges": ranges,
            "intensities": [],
        }
    )


def encode_grid(
    time_ns: int,
    x_m: float,
    y_m: float,
    cell_m: float,
    columns: int,
    cells: bytes,
) -> bytes:
    """foxglove.Grid in :data:`GRID_FRAME`: one UINT8 ``occupancy`` a cell (percent, 255 never
    seen), row 0 the southernmost, its corner at (``x_m``, ``y_m``)."""
    return orjson.dumps(
        {
            "timestamp": stamp(time_ns),
            "frame_id": GRID_FRAME,
            "pose": {
                "position": {"x": x_m, "y": y_m, "z": 0.0},
                "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0},
            },
            "column_count": columns,
            "cell_size": {"x": cell_m, "y": cell_m},
            "row_stride": columns,
            "cell_stride": 1,
            "fields": [{"name": "occupancy", "offset": 0, "type": 1}],
            "data": base64.b64encode(cells).decode("ascii"),
        }
    )


def encode_video(time_ns: int, access_unit: bytes) -> bytes:
    """foxglove.CompressedVideo: one H.264 access unit, Annex B."""
    return orjson.dumps(
        {
            "timestamp": stamp(time_ns),
            "frame_id": "navcam",
            "data": base64.b64encode(access_unit).decode("ascii"),
            "format": "h264",
        }
    )


def encode_log(time_ns: int, level: int, name: str, message: str) -> bytes:
    return orjson.dumps(
        {
            "timestamp": stamp(time_ns),
            "level": level,
            "message": message,
            "name": name,
            "file": "",
            "line": 0,
        }
    )


def encode_geojson(geojson: Any) -> bytes:
    """foxglove.GeoJSON: the document as a string."""
    text = geojson if isinstance(geojson, str) else orjson.dumps(geojson).decode()
    return orjson.dumps({"geojson": text})


def encode_path(points: typing.Sequence[tuple[float, float]]) -> bytes:
    """A planned path ([lat, lon] points) as a GeoJSON LineString (lon, lat order)."""
    feature = {
        "type": "Feature",
        "properties": {"name": "route"},
        "geometry": {"type": "LineString", "coordinates": [[lon, lat] for lat, lon in points]},
    }
    return encode_geojson({"type": "FeatureCollection", "features": [feature]})


def encode_section(value: Section) -> bytes:
    return orjson.dumps(section_to_json(value))


REDACTED = "<session>"
"""What a session token in a command's payload is recorded as."""


def encode_command(message: CommandReceived) -> bytes:
    """The command with its sender's station id, never its session token: a token is a live
    credential, and whoever holds a recording could act as that session."""
    payload = message.payload
    if message.session_id:
        payload = payload.replace(message.session_id, REDACTED)
    return encode_json(
        {
            "kind": message.kind,
            "name": message.name,
            "payload": payload,
            "station": message.station_id,
            "accepted": message.accepted,
            "reason": message.reason,
        }
    )


def encode_velocity(linear: float, angular: float) -> bytes:
    return encode_json({"linear": linear, "angular": angular})


def encode_json(value: Any) -> bytes:
    return orjson.dumps(value)
