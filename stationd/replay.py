"""Replaying a recording at the station (issue 23), sans-IO over a finished MCAP file: its index
(time span, channels, the track, the keyframes) and the state at any time (the position, the
telemetry sections, the log up to then, and the NavCam's access units from the keyframe
before it), read through the file's chunk index: a seek reads only the chunks it needs.
Blocking file work: callers run these in a thread."""

from __future__ import annotations

import base64
import json
from pathlib import Path
from typing import Any

from mcap.reader import make_reader

from brasidas.recording import schemas
from brasidas.recording.writer import summary_channels

TRACK_POINTS = 2000
"""The track is thinned to at most this many points (an hour of 10 Hz poses is 36 000)."""
STATE_WINDOW_NS = 5_000_000_000
"""Telemetry older than this before the time asked is not shown (a section that stopped)."""
VIDEO_WINDOW_NS = 3_000_000_000
"""Where the keyframe before a time is looked for (the NavCam has one every second)."""
LOG_WINDOW_NS = 120_000_000_000
LOG_LINES = 30
PLOTS: dict[str, tuple[str, str]] = {
    "speed m/s": ("/telemetry/pose", "speed"),
    "battery V": ("/telemetry/battery", "volts"),
    "motor linear": ("/motor/command", "linear"),
}
"""What the view plots along the timeline: a label, then the channel and the field."""


def _is_keyframe(access_unit: bytes) -> bool:
    """An IDR slice (NAL type 5) or an SPS (7) after a start code."""
    index = access_unit.find(b"\x00\x00\x01")
    while index != -1 and index + 3 < len(access_unit):
        if access_unit[index + 3] & 0x1F in (5, 7):
            return True
        index = access_unit.find(b"\x00\x00\x01", index + 3)
    return False


def recording_index(path: Path) -> dict[str, Any]:
    """Time span (ns), channels with their schema and count, the track ([t, lat, lon])."""
    with open(path, "rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        if summary is None or summary.statistics is None:
            raise ValueError(f"{path.name} has no summary (not a finished recording)")
        stats = summary.statistics
        channels = summary_channels(summary)
        source = schemas.POSE.topic if schemas.POSE.topic in channels else schemas.GPS.topic
        track = [
            [message.log_time, *_lat_lon(message.data)]
            for _s, _c, message in reader.iter_messages(topics=[source])
        ]
        plots = _plots(reader, channels)
    step = max(1, len(track) // TRACK_POINTS)
    return {
        "plots": plots,
        "start_ns": stats.message_start_time,
        "end_ns": stats.message_end_time,
        "channels": channels,
        "track_topic": source,
        "track": track[::step],
        "video": schemas.NAVCAM.topic in channels,
    }


def _plots(reader: Any, channels: dict[str, Any]) -> dict[str, list[list[float]]]:
    """Each plot's [t, value] points, thinned like the track."""
    wanted = {topic for topic, _field in PLOTS.values() if topic in channels}
    series: dict[str, list[list[float]]] = {label: [] for label in PLOTS}
    if not wanted:
        return series
    for _s, channel, message in reader.iter_messages(topics=list(wanted)):
        value = json.loads(message.data)
        for label, (topic, field) in PLOTS.items():
            item = value.get(field) if topic == channel.topic else None
            if isinstance(item, int | float) and not isinstance(item, bool):
                series[label].append([message.log_time, float(item)])
    for label, points in series.items():
        series[label] = points[:: max(1, len(points) // TRACK_POINTS)]
    return series


def _lat_lon(data: bytes) -> list[float]:
    fix = json.loads(data)
    return [float(fix["latitude"]), float(fix["longitude"])]


def recording_state(path: Path, time_ns: int, frames_after_ns: int | None = None) -> dict[str, Any]:
    """What the robot knew and saw at ``time_ns``: the latest of each channel within
    :data:`STATE_WINDOW_NS` (position, telemetry sections), the log up to then, and the NavCam
    access units from the last keyframe to the frame shown then (base64, oldest first).

    While playing, the console's decoder already has every unit up to ``frames_after_ns``:
    then (within :data:`VIDEO_WINDOW_NS`) the units after it are sent, keyframes or not, and
    the answer's ``frames_after_ns`` says so (None: from the keyframe)."""
    latest: dict[str, tuple[int, Any]] = {}
    log: list[dict[str, Any]] = []
    frames: list[tuple[int, bytes]] = []
    with open(path, "rb") as stream:
        reader = make_reader(stream)
        for _s, channel, message in reader.iter_messages(
            starting_at=time_ns - STATE_WINDOW_NS, ending_at=time_ns
        ):
            if channel.topic in (schemas.NAVCAM.topic, schemas.LOG_CHANNEL.topic):
                continue
            latest[channel.topic] = (message.log_time, json.loads(message.data))
        for _s, _c, message in reader.iter_messages(
            topics=[schemas.LOG_CHANNEL.topic],
            starting_at=time_ns - LOG_WINDOW_NS,
            ending_at=time_ns,
        ):
            entry = json.loads(message.data)
            log.append(
                {"time_ns": message.log_time, "level": entry["level"], "text": entry["message"]}
            )
        following = frames_after_ns is not None and (
            time_ns - VIDEO_WINDOW_NS <= frames_after_ns < time_ns
        )
        for _s, _c, message in reader.iter_messages(
            topics=[schemas.NAVCAM.topic],
            starting_at=frames_after_ns + 1
            if following and frames_after_ns is not None
            else time_ns - VIDEO_WINDOW_NS,
            ending_at=time_ns,
        ):
            unit = base64.b64decode(json.loads(message.data)["data"])
            if following:
                frames.append((message.log_time, unit))
                continue
            if _is_keyframe(unit):
                frames = []
            if frames or _is_keyframe(unit):
                frames.append((message.log_time, unit))
    position = latest.get(schemas.POSE.topic) or latest.get(schemas.GPS.topic)
    return {
        "time_ns": time_ns,
        "position": None
        if position is None
        else {
            "time_ns": position[0],
            "lat": position[1]["latitude"],
            "lon": position[1]["longitude"],
        },
        "telemetry": {
            topic.removeprefix("/telemetry/"): value
            for topic, (_t, value) in latest.items()
            if topic.startswith("/telemetry/")
        },
        "log": log[-LOG_LINES:],
        "frames": [
            {"time_ns": t, "data": base64.b64encode(unit).decode("ascii")} for t, unit in frames
        ],
        "frames_after_ns": frames_after_ns if following else None,
    }
