"""The telemetry schema: one typed dataclass per snapshot section, shared by sender and readers.

The platform builds each section as one of these dataclasses; :func:`snapshot_to_wire` turns
a snapshot into the compact map the datagrams carry (:mod:`brasidas.codecs.telemetry`), each
section under its short ``WIRE`` key and each field under the short key of its metadata. The
station turns the map back into dataclasses with :func:`snapshot_from_wire` (a malformed
section becomes that section's :class:`SectionError`, never an exception), the local API
hands them out by their long names (:func:`snapshot_to_json`), and the status view and
annunciator read them as attributes. :func:`schema_document` describes all of it as JSON for
the browser console. Any change here bumps :data:`SCHEMA_VERSION`, which every datagram's
header carries.

A section is either a value, ``None`` (the platform has no such data: no GPS fitted) or a
:class:`SectionError` (its source failed; on the wire ``{"!": "why"}``).
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar, TypeVar

SCHEMA_VERSION = 18
"""Version of the schema (and the datagram layout); the first byte of every datagram.
4: the failsafe, speed_cap and turret sections, the velocity link's ``held`` drops.
5: the lights' ``errors`` (GPIO lines), the turret's ``streams``.
6: the autonomy section's ``map_rev``.
7: the turret's ``error`` (its line cannot be opened, or went away).
8: the admission section (strangers refused and closed, issue 19).
9: the recorder section (recording, or stopped and why; its drops).
11: the arming section (armed, pre-arm reasons, autostart countdown, last stop; issue 27).
12: the perception section (the lidar: scan rate, nearest obstacle, speed limit and why).
13: the autonomy section's ``home`` (the route's home, else the first fix; issue 31).
14: perception's localization (source, uncertainty) and GPS gate (accepted, refused, why).
15: the lidar_view section (the scan in 5° sectors, the fused pose, the grid's revision).
18: perception's ``map_place`` (without GPS: placed in the saved map, searching, or why not)."""
ERROR_KEY = "!"
"""A section's wire map holding only this key is that section's error."""
STALE_PERIODS = 3.0
"""A sensor reading older than this many of its sensor's periods is stale."""
MIN_STALE_S = 1.0
"""...but never stale sooner than this (a loaded computer delays a 10 Hz reading a little)."""


class SchemaError(ValueError):
    """A section that does not match the schema (wrong type, missing required field)."""


def wire(key: str, *, unit: str = "", doc: str = "") -> dict[str, str]:
    """Field metadata: the compact key on the wire, the unit and a one-line meaning."""
    return {"wire": key, "unit": unit, "doc": doc}


@dataclass(frozen=True)
class SectionError:
    """The section's source failed on the platform; the rest of the snapshot is unaffected."""

    error: str


class Section:
    """Base of every section: ``NAME`` (API and console) and ``WIRE`` (datagrams) keys."""

    NAME: ClassVar[str]
    WIRE: ClassVar[str]


S = TypeVar("S", bound=Section)


def stale_after(rate_hz: float) -> float | None:
    """Seconds after which a reading of a sensor sampled at ``rate_hz`` is stale (None: never)."""
    if rate_hz <= 0:
        return None
    return max(MIN_STALE_S, STALE_PERIODS / rate_hz)


def age_ms(now: float, stamp: float) -> int:
    """Milliseconds since ``stamp`` (both monotonic seconds), never negative."""
    return max(0, round((now - stamp) * 1000))


# --------------------------------------------------------------------------- sections


@dataclass(frozen=True)
class Override(Section):
    """Who drives: the mode and the station holding the manual override."""

    NAME = "override"
    WIRE = "ov"
    mode: str = field(default="autonomous", metadata=wire("m", doc="autonomous or teleop"))
    engaged: bool = field(default=False, metadata=wire("e", doc="manual override engaged"))
    station: str | None = field(default=None, metadata=wire("s", doc="holder of the override"))


@dataclass(frozen=True)
class Lights(Section):
    NAME = "lights"
    WIRE = "li"
    main: bool = field(default=False, metadata=wire("m"))
    positional: bool = field(default=False, metadata=wire("p"))
    errors: dict[str, str] = field(
        default_factory=dict,
        metadata=wire("e", doc="why a light cannot be switched (GPIO chip missing, line busy)"),
    )


@dataclass(frozen=True)
class Battery(Section):
    """The pack, from the controller's status poll (?e)."""

    NAME = "battery"
    WIRE = "bat"
    volts: float | None = field(default=None, metadata=wire("v", unit="V"))
    level: str | None = field(default=None, metadata=wire("l", doc="low, medium or high"))
    monitor: bool = field(default=True, metadata=wire("m", doc="battery monitor (20.4) on"))
    age_ms: int | None = field(default=None, metadata=wire("age", unit="ms"))
    stale: bool = field(default=False, metadata=wire("old", doc="older than a few poll periods"))


@dataclass(frozen=True)
class Controller(Section):
    """The AX3500 motor controller: link and polled readings (?m heatsinks, ?a amps)."""

    NAME = "controller"
    WIRE = "ctl"
    connected: bool = field(default=False, metadata=wire("c"))
    temps_c: tuple[float, ...] | None = field(default=None, metadata=wire("t", unit="°C"))
    amps: tuple[float, ...] | None = field(default=None, metadata=wire("a", unit="A"))
    internal_volts: float | None = field(default=None, metadata=wire("iv", unit="V"))
    error: str = field(default="", metadata=wire("err"))
    age_ms: int | None = field(default=None, metadata=wire("age", unit="ms"))
    stale: bool = field(default=False, metadata=wire("old"))


@dataclass(frozen=True)
class Motor(Section):
    """The motor driver's send scheduler: desired and acknowledged channel levels."""

    NAME = "motor"
    WIRE = "mtr"
    connected: bool = field(default=False, metadata=wire("c"))
    desired: tuple[int, ...] = field(default=(), metadata=wire("d"))
    acknowledged: tuple[int | None, ...] = field(default=(), metadata=wire("a"))
    error: str = field(default="", metadata=wire("err"))


@dataclass(frozen=True)
class GpsReader(Section):
    """The GPS reader's counters (nested in :class:`Gps`)."""

    NAME = "stats"
    WIRE = "st"
    connected: bool = field(default=False, metadata=wire("c"))
    sentences: int = field(default=0, metadata=wire("n"))
    fixes: int = field(default=0, metadata=wire("f"))
    dropped: dict[str, int] = field(default_factory=dict, metadata=wire("d"))
    incomplete_epochs: int = field(default=0, metadata=wire("ie"))
    error: str = field(default="", metadata=wire("err"))


@dataclass(frozen=True)
class Gps(Section):
    """The last fix, whether it still holds, and the reader's counters."""

    NAME = "gps"
    WIRE = "gps"
    fix: bool = field(default=False, metadata=wire("f", doc="a fix holds now"))
    lat: float | None = field(default=None, metadata=wire("la", unit="°"))
    lon: float | None = field(default=None, metadata=wire("lo", unit="°"))
    alt: float | None = field(default=None, metadata=wire("al", unit="m"))
    speed: float | None = field(default=None, metadata=wire("sp", unit="m/s"))
    course: float | None = field(default=None, metadata=wire("co", unit="°"))
    quality: int | None = field(default=None, metadata=wire("q"))
    sats: int | None = field(default=None, metadata=wire("n"))
    hdop: float | None = field(default=None, metadata=wire("h"))
    time: str | None = field(default=None, metadata=wire("t", doc="UTC of the fix"))
    lost_for_s: float | None = field(default=None, metadata=wire("lost", unit="s"))
    stats: GpsReader | None = field(default=None, metadata=wire("st"))
    age_ms: int | None = field(default=None, metadata=wire("age", unit="ms"))
    stale: bool = field(default=False, metadata=wire("old"))


@dataclass(frozen=True)
class Imu(Section):
    """The IMU driver's health (nested in :class:`Attitude`)."""

    NAME = "imu"
    WIRE = "imu"
    ok: bool = field(default=False, metadata=wire("ok"))
    error: str = field(default="", metadata=wire("err"))
    temp_c: float | None = field(default=None, metadata=wire("t", unit="°C"))
    samples: int = field(default=0, metadata=wire("n"))
    read_errors: int = field(default=0, metadata=wire("re"))
    calibrated: bool = field(default=False, metadata=wire("cal"))
    fifo_overflows: int = field(default=0, metadata=wire("ov"))


@dataclass(frozen=True)
class Attitude(Section):
    """Orientation from the IMU's filter, and the IMU's health."""

    NAME = "attitude"
    WIRE = "att"
    roll: float | None = field(default=None, metadata=wire("r", unit="°"))
    pitch: float | None = field(default=None, metadata=wire("p", unit="°"))
    yaw: float | None = field(default=None, metadata=wire("y", unit="°"))
    q: tuple[float, ...] | None = field(default=None, metadata=wire("q", doc="w, x, y, z"))
    imu: Imu | None = field(default=None, metadata=wire("imu"))
    age_ms: int | None = field(default=None, metadata=wire("age", unit="ms"))
    stale: bool = field(default=False, metadata=wire("old"))


@dataclass(frozen=True)
class Computer(Section):
    """The platform's computer."""

    NAME = "computer"
    WIRE = "cpu"
    cpu_temp_c: float | None = field(default=None, metadata=wire("t", unit="°C"))
    load: tuple[float, ...] | None = field(default=None, metadata=wire("ld"))
    mem_free_mb: float | None = field(default=None, metadata=wire("mf", unit="MB"))
    mem_total_mb: float | None = field(default=None, metadata=wire("mt", unit="MB"))


@dataclass(frozen=True)
class Link(Section):
    """Sessions and telemetry streams open on the platform."""

    NAME = "link"
    WIRE = "lnk"
    sessions: int = field(default=0, metadata=wire("s"))
    telemetry_streams: int = field(default=0, metadata=wire("t"))


@dataclass(frozen=True)
class VelocityLink(Section):
    """The velocity receiver's counters."""

    NAME = "velocity_link"
    WIRE = "vel"
    accepted: int = field(default=0, metadata=wire("a"))
    dropped: dict[str, int] = field(default_factory=dict, metadata=wire("d"))
    last_count: int | None = field(default=None, metadata=wire("n"))
    age_ms: float | None = field(default=None, metadata=wire("g"))
    """The last accepted packet's age on arrival (its send time, ``$PVEL``'s ``sent``)."""
    age_max_ms: float | None = field(default=None, metadata=wire("x"))
    """The oldest accepted packet of the last second: the speed cap's command latency."""


@dataclass(frozen=True)
class Motion(Section):
    """Which source drives the motors, the teleop deadman, the last motor command."""

    NAME = "motion"
    WIRE = "mot"
    mode: str = field(default="autonomous", metadata=wire("m"))
    deadman: bool = field(default=False, metadata=wire("d"))
    linear: float = field(default=0.0, metadata=wire("l"))
    angular: float = field(default=0.0, metadata=wire("a"))


@dataclass(frozen=True)
class Failsafe(Section):
    """The failsafe ladder (normal, hold, released), why, and who holds control."""

    NAME = "failsafe"
    WIRE = "fs"
    step: str = field(default="normal", metadata=wire("s"))
    reason: str = field(default="", metadata=wire("r"))
    controller: str | None = field(default=None, metadata=wire("c"))
    """The station holding control (command authority), None when nobody does."""


@dataclass(frozen=True)
class SpeedLimit(Section):
    """The teleop speed cap for the measured latency, its inputs and its reason."""

    NAME = "speed_cap"
    WIRE = "cap"
    cap_kmh: float = field(default=0.0, metadata=wire("k"))
    video_ms: float | None = field(default=None, metadata=wire("v"))
    command_ms: float | None = field(default=None, metadata=wire("c"))
    reason: str = field(default="", metadata=wire("r"))


@dataclass(frozen=True)
class Turret(Section):
    """The turret payload: servos and trigger by the last acknowledgement, line counters."""

    NAME = "turret"
    WIRE = "tur"
    connected: bool = field(default=False, metadata=wire("k"))
    azimuth: float | None = field(default=None, metadata=wire("a"))
    elevation: float | None = field(default=None, metadata=wire("e"))
    trigger: bool = field(default=False, metadata=wire("t"))
    counters: dict[str, int] = field(default_factory=dict, metadata=wire("n"))
    """Sent, acked, resent, unacked, refused, watchdog releases, made safe."""
    streams: dict[str, str] = field(
        default_factory=dict, metadata=wire("s", doc="its own streams (the thermal camera): state")
    )
    error: str = field(default="", metadata=wire("r", doc="why its line is not open"))


@dataclass(frozen=True)
class Streams(Section):
    """Media streams by name, with their state (idle, playing, failed...)."""

    NAME = "streams"
    WIRE = "med"
    states: dict[str, str] = field(default_factory=dict, metadata=wire("s"))


@dataclass(frozen=True)
class Platforms(Section):
    """The other platforms heard online (R-9), with the age of their last beacon."""

    NAME = "platforms"
    WIRE = "pf"
    age_s: dict[str, float] = field(default_factory=dict, metadata=wire("a", unit="s"))


@dataclass(frozen=True)
class Diagnostics(Section):
    """Counters, sent only while diagnostics are on (command 20.0)."""

    NAME = "diagnostics"
    WIRE = "dia"
    actor_restarts: dict[str, int] = field(default_factory=dict, metadata=wire("ar"))
    bus_delivery_errors: int = field(default=0, metadata=wire("be"))
    rpc: dict[str, int] = field(default_factory=dict, metadata=wire("rpc"))
    commands: dict[str, int] = field(default_factory=dict, metadata=wire("cmd"))
    auth_failures: int | None = field(default=None, metadata=wire("af"))
    telemetry: dict[str, int] = field(default_factory=dict, metadata=wire("tm"))
    section_errors: dict[str, int] = field(default_factory=dict, metadata=wire("se"))
    subsystems: dict[str, dict[str, int]] = field(default_factory=dict, metadata=wire("ss"))


@dataclass(frozen=True)
class Admission(Section):
    """What signaling refused or closed of connections without a session (issue 19).

    Always sent, small: only the counters that are not zero."""

    NAME = "admission"
    WIRE = "adm"
    counters: dict[str, int] = field(
        default_factory=dict,
        metadata=wire(
            "n",
            doc="since start, the non-zero ones: refused_host, evicted_host, evicted, refused_full, "
            "header_timeouts, body_timeouts, idle_timeouts, slow_readers, out_of_descriptors, "
            "throttled, refused_batches",
        ),
    )
    strangers: int = field(default=0, metadata=wire("s", doc="connections without a session"))
    refusing: str = field(
        default="", metadata=wire("h", doc="the address refused most in the window, or empty")
    )
    refused: int = field(default=0, metadata=wire("r", doc="its refusals in the window"))
    window_s: float = field(default=0.0, metadata=wire("w", unit="s"))


@dataclass(frozen=True)
class Pose(Section):
    """Where the robot is: localization from GPS, the IMU and the commanded motion (issue 12)."""

    NAME = "pose"
    WIRE = "pos"
    lat: float | None = field(default=None, metadata=wire("la", unit="°"))
    lon: float | None = field(default=None, metadata=wire("lo", unit="°"))
    heading: float | None = field(
        default=None, metadata=wire("h", unit="°", doc="compass; null until known")
    )
    speed: float = field(default=0.0, metadata=wire("sp", unit="m/s"))
    sigma_m: float | None = field(
        default=None, metadata=wire("sg", unit="m", doc="position uncertainty (1 sigma)")
    )
    fix_age_s: float | None = field(default=None, metadata=wire("fa", unit="s"))
    source: str = field(default="", metadata=wire("src", doc="e.g. gps+imu"))


@dataclass(frozen=True)
class Autonomy(Section):
    """The patrol (issue 12): its state, target, lap, why, and the planned path."""

    NAME = "autonomy"
    WIRE = "aut"
    state: str = field(
        default="idle", metadata=wire("s", doc="idle, patrolling, suspended, holding or stopped")
    )
    enabled: bool = field(default=True, metadata=wire("on", doc="patrol automation (10.8) on"))
    waypoint: int | None = field(default=None, metadata=wire("w", doc="index of the target"))
    waypoints: int = field(default=0, metadata=wire("n"))
    distance_m: float | None = field(default=None, metadata=wire("d", unit="m"))
    lap: int = field(default=0, metadata=wire("l"))
    reason: str = field(default="", metadata=wire("r"))
    path: tuple[tuple[float, ...], ...] = field(
        default=(), metadata=wire("p", unit="°", doc="planned path, [lat, lon] points")
    )
    map_rev: int = field(
        default=0,
        metadata=wire("m", doc="changes with the area map (loaded, keep-outs added or removed)"),
    )
    map_error: str = field(
        default="", metadata=wire("me", doc="why the stored map (map.file) was refused at start")
    )
    home: tuple[float, ...] = field(
        default=(),
        metadata=wire(
            "hm", unit="°", doc="[lat, lon]: the route's home, else the first fix; empty: none yet"
        ),
    )


@dataclass(frozen=True)
class Arming(Section):
    """Armed or not (disarmed: motors held at zero), why arming would be refused, the
    autostart countdown and who stopped the robot last (issue 27)."""

    NAME = "arming"
    WIRE = "arm"
    armed: bool = field(default=False, metadata=wire("a", doc="motors may move"))
    ready: bool = field(default=False, metadata=wire("r", doc="the pre-arm checks pass"))
    prearm: tuple[str, ...] = field(
        default=(), metadata=wire("p", doc="failing pre-arm checks (PreArm: no GPS fix)")
    )
    countdown_s: float | None = field(
        default=None, metadata=wire("c", unit="s", doc="autostart arms and patrols in this")
    )
    last_stop: str = field(default="", metadata=wire("s", doc="who stopped the robot, when"))


@dataclass(frozen=True)
class Automation(Section):
    """Onboard automations switched on or off (R-3: 10.8-10.10, 20.0, 20.4), by name."""

    NAME = "automation"
    WIRE = "aon"
    switches: dict[str, bool] = field(default_factory=dict, metadata=wire("s"))


@dataclass(frozen=True)
class RecorderStatus(Section):
    """The flight recorder (issue 23): recording, or stopped and why; what it dropped."""

    NAME = "recorder"
    WIRE = "rec"
    recording: bool = field(default=False, metadata=wire("r"))
    reason: str = field(
        default="", metadata=wire("w", doc="why it stopped: disk full, a write failed, quota")
    )
    dropped: int = field(
        default=0, metadata=wire("d", doc="messages dropped: the writer could not keep up")
    )
    not_recorded: int = field(
        default=0, metadata=wire("n", doc="messages not recorded while it was stopped")
    )


@dataclass(frozen=True)
class Perception(Section):
    """The lidar (issue 30): its scans, the nearest obstacle, and the speed limit it sets."""

    NAME = "perception"
    WIRE = "per"
    connected: bool = field(default=False, metadata=wire("c", doc="the sensor's line is open"))
    scan_hz: float = field(default=0.0, metadata=wire("hz", unit="Hz", doc="revolutions a second"))
    points_used: int = field(
        default=0, metadata=wire("pu", doc="returns in obstacles in the last scan")
    )
    nearest_m: float | None = field(
        default=None, metadata=wire("nd", unit="m", doc="nearest obstacle from the centre")
    )
    nearest_bearing_deg: float | None = field(
        default=None, metadata=wire("nb", unit="°", doc="its bearing, clockwise from forward")
    )
    forward_limit: float = field(
        default=1.0, metadata=wire("fl", doc="forward speed allowed, fraction of top speed")
    )
    reverse_limit: float = field(default=1.0, metadata=wire("rl", doc="reverse, likewise"))
    reason: str = field(default="", metadata=wire("r", doc="why it slows or stops the robot"))
    obstacles: tuple[tuple[float, ...], ...] = field(
        default=(),
        metadata=wire("o", doc="[bearing °, range m, radius m] of each obstacle (12 nearest)"),
    )
    crc_errors: int = field(default=0, metadata=wire("ce", doc="corrupt frames dropped"))
    localization: str = field(
        default="",
        metadata=wire("ls", doc="gps+lidar, lidar (no GPS), prior (dead reckoning), none, or off"),
    )
    position_sigma_m: float | None = field(
        default=None, metadata=wire("lu", unit="m", doc="the fused position's uncertainty")
    )
    gps_accepted: int = field(default=0, metadata=wire("ga", doc="GPS fixes fused"))
    gps_rejected: int = field(default=0, metadata=wire("gr", doc="GPS fixes refused by the gate"))
    gps_refusal: str = field(
        default="", metadata=wire("gx", doc="why GPS is refused now (jump, drag), never followed")
    )
    map_place: str = field(
        default="",
        metadata=wire(
            "mp", doc="without GPS: placed in the saved map (its fit), searching, or why it holds"
        ),
    )


@dataclass(frozen=True)
class LidarView(Section):
    """What the operator is shown of the lidar (:mod:`brasidas.perception.view`): the latest
    scan, coarse, the fused pose, and the occupancy grid's revision (the grid itself is asked
    for with ``get_grid``: too large for a datagram)."""

    NAME = "lidar_view"
    WIRE = "lv"
    ranges_dm: tuple[int, ...] = field(
        default=(),
        metadata=wire(
            "r", doc="nearest return in each 5° sector clockwise from forward, dm; 0 none"
        ),
    )
    fused_lat: float | None = field(default=None, metadata=wire("la", unit="°", doc="fused pose"))
    fused_lon: float | None = field(default=None, metadata=wire("lo", unit="°"))
    fused_heading_deg: float | None = field(
        default=None, metadata=wire("hd", unit="°", doc="fused heading, clockwise from north")
    )
    grid_rev: int = field(
        default=0, metadata=wire("g", doc="the occupancy grid's revision (0: none yet)")
    )


TOGETHER: tuple[frozenset[str], ...] = (frozenset({Pose.WIRE, Perception.WIRE, LidarView.WIRE}),)
"""Wire keys a split snapshot keeps in one datagram: the scan and its obstacles are relative
to the robot, drawn around the pose; a pose from another datagram (lost, or not yet come)
would place them wrong (the station merges datagrams section by section)."""

SECTIONS: tuple[type[Section], ...] = (
    Override,
    Lights,
    Battery,
    Controller,
    Motor,
    Gps,
    Attitude,
    Computer,
    Link,
    VelocityLink,
    Motion,
    Failsafe,
    SpeedLimit,
    Turret,
    Streams,
    Platforms,
    Pose,
    Autonomy,
    Automation,
    Arming,
    Admission,
    RecorderStatus,
    Perception,
    LidarView,
    Diagnostics,
)
"""Every top-level section, in snapshot order."""
BY_WIRE: dict[str, type[Section]] = {cls.WIRE: cls for cls in SECTIONS}
BY_NAME: dict[str, type[Section]] = {cls.NAME: cls for cls in SECTIONS}

SectionValue = Section | SectionError | None


@dataclass(frozen=True)
class Snapshot:
    """A decoded snapshot: each section a value, an error, or absent/None."""

    sections: Mapping[type[Section], SectionValue] = field(default_factory=dict)

    def get(self, cls: type[S]) -> S | None:
        """The section's value; None when absent, null or failed."""
        value = self.sections.get(cls)
        return value if isinstance(value, cls) else None

    def error(self, cls: type[Section]) -> str | None:
        """Why the section failed on the platform, or None."""
        value = self.sections.get(cls)
        return value.error if isinstance(value, SectionError) else None


# --------------------------------------------------------------------------- conversion


def section_to_wire(value: Section) -> dict[str, Any]:
    """Compact form: wire keys; fields at their default (None, 0, "", empty) left out."""
    out: dict[str, Any] = {}
    for f in _fields(type(value)):
        item = getattr(value, f.name)
        if _is_default(f, item):
            continue
        out[f.metadata["wire"]] = _plain(item, section_to_wire)
    return out


def section_to_json(value: Section) -> dict[str, Any]:
    """Long form (field names, every field): the station's local API and the console."""
    return {f.name: _plain(getattr(value, f.name), section_to_json) for f in _fields(type(value))}


def section_from_wire(cls: type[S], data: Any) -> S:
    """The section from its wire map; raises :class:`SchemaError`."""
    return _build(cls, data, wire_keys=True)


def section_from_json(cls: type[S], data: Any) -> S:
    """The section from its long form; raises :class:`SchemaError`."""
    return _build(cls, data, wire_keys=False)


def snapshot_to_wire(snapshot: Mapping[type[Section], SectionValue]) -> dict[str, Any]:
    """The sections map a datagram carries."""
    out: dict[str, Any] = {}
    for cls, value in snapshot.items():
        out[cls.WIRE] = _value_to(value, section_to_wire)
    return out


def snapshot_to_json(snapshot: Mapping[type[Section], SectionValue]) -> dict[str, Any]:
    """Long names; a failed section is ``{"error": why}``."""
    return {cls.NAME: _value_to(value, section_to_json, "error") for cls, value in snapshot.items()}


def snapshot_from_wire(sections: Mapping[str, Any]) -> tuple[Snapshot, list[str]]:
    """Decode a datagram's sections; returns the snapshot and the unknown wire keys.

    A section that does not match the schema becomes a :class:`SectionError` naming why.
    """
    return _snapshot_from(sections, BY_WIRE, True, ERROR_KEY)


def snapshot_from_json(sections: Mapping[str, Any]) -> Snapshot:
    """The local API's long form back into sections (the status view)."""
    return _snapshot_from(sections, BY_NAME, False, "error")[0]


def schema_document() -> dict[str, Any]:
    """The schema as JSON: every section's names, wire keys, types and units (the console)."""
    return {
        "version": SCHEMA_VERSION,
        "error_key": ERROR_KEY,
        "sections": {cls.NAME: _describe(cls) for cls in SECTIONS},
    }


# --------------------------------------------------------------------------- internals


def _value_to(value: SectionValue, convert: Any, error_key: str = ERROR_KEY) -> Any:
    if value is None:
        return None
    if isinstance(value, SectionError):
        return {error_key: value.error}
    return convert(value)


def _snapshot_from(
    sections: Mapping[str, Any], table: Mapping[str, type[Section]], wire_keys: bool, error_key: str
) -> tuple[Snapshot, list[str]]:
    result: dict[type[Section], SectionValue] = {}
    unknown: list[str] = []
    for key, data in sections.items():
        cls = table.get(key)
        if cls is None:
            unknown.append(key)
            continue
        if data is None:
            result[cls] = None
        elif isinstance(data, dict) and set(data) == {error_key}:
            result[cls] = SectionError(str(data[error_key]))
        else:
            try:
                result[cls] = _build(cls, data, wire_keys=wire_keys)
            except SchemaError as err:
                result[cls] = SectionError(f"malformed: {err}")
    return Snapshot(result), unknown


def _is_default(f: dataclasses.Field[Any], item: Any) -> bool:
    if f.default is not dataclasses.MISSING:
        return bool(item == f.default and type(item) is type(f.default))
    if f.default_factory is not dataclasses.MISSING:
        return bool(item == f.default_factory())
    return False


def _plain(item: Any, nested: Any) -> Any:
    if isinstance(item, Section):
        return nested(item)
    if isinstance(item, tuple):
        return list(item)
    if isinstance(item, dict):
        return {k: _plain(v, nested) for k, v in item.items()}
    return item


_HINTS: dict[type[Section], dict[str, Any]] = {}
_FIELDS: dict[type[Section], tuple[dataclasses.Field[Any], ...]] = {}


def _fields(cls: type[Section]) -> tuple[dataclasses.Field[Any], ...]:
    """The section's fields, looked up once. ``dataclasses.fields`` builds its tuple from a
    generator at each call: CPython 3.11 makes a 10-slot tuple and shrinks it, so the tuple
    freed later lands on the free list of its final size, which it has not come from. Done for
    every section of every snapshot (5 Hz a station), that filled the tuple free lists to their
    cap (2000 each) over the first 8 minutes: 1.2 MB a process gained for nothing."""
    found = _FIELDS.get(cls)
    if found is None:
        found = _FIELDS[cls] = dataclasses.fields(cls)  # type: ignore[arg-type]
    return found


def _hints(cls: type[Section]) -> dict[str, Any]:
    hints = _HINTS.get(cls)
    if hints is None:
        hints = _HINTS[cls] = typing.get_type_hints(cls)
    return hints


def _build(cls: type[S], data: Any, *, wire_keys: bool) -> S:
    if not isinstance(data, dict):
        raise SchemaError(f"{cls.NAME}: not a map")
    hints = _hints(cls)
    values: dict[str, Any] = {}
    for f in _fields(cls):
        key = f.metadata["wire"] if wire_keys else f.name
        if key not in data:
            continue
        values[f.name] = _convert(hints[f.name], data[key], f"{cls.NAME}.{f.name}", wire_keys)
    return cls(**values)


def _convert(tp: Any, value: Any, path: str, wire_keys: bool) -> Any:
    origin = typing.get_origin(tp)
    if origin is types.UnionType or origin is typing.Union:
        args = typing.get_args(tp)
        if value is None and type(None) in args:
            return None
        (inner,) = [arg for arg in args if arg is not type(None)]
        return _convert(inner, value, path, wire_keys)
    if tp is bool:
        if isinstance(value, bool):
            return value
    elif tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif tp is float:
        if isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value):
            return float(value)
    elif tp is str:
        if isinstance(value, str):
            return value
    elif origin is tuple:
        if isinstance(value, list | tuple):
            (item_type, _ellipsis) = typing.get_args(tp)
            return tuple([_convert(item_type, item, path, wire_keys) for item in value])
    elif origin is dict:
        if isinstance(value, dict):
            _key_type, item_type = typing.get_args(tp)
            return {
                str(k): _convert(item_type, v, f"{path}.{k}", wire_keys) for k, v in value.items()
            }
    elif isinstance(tp, type) and issubclass(tp, Section):
        return _build(tp, value, wire_keys=wire_keys)
    raise SchemaError(f"{path}: expected {_type_name(tp)}, got {type(value).__name__}")


def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is types.UnionType or origin is typing.Union:
        return " | ".join(_type_name(arg) for arg in typing.get_args(tp))
    if tp is type(None):
        return "null"
    if origin is tuple:
        return f"list[{_type_name(typing.get_args(tp)[0])}]"
    if origin is dict:
        return f"map[{_type_name(typing.get_args(tp)[1])}]"
    if isinstance(tp, type) and issubclass(tp, Section):
        return tp.NAME
    return {bool: "bool", int: "int", float: "float", str: "str"}.get(tp, str(tp))


def _describe(cls: type[Section]) -> dict[str, Any]:
    hints = _hints(cls)
    fields: dict[str, Any] = {}
    for f in dataclasses.fields(cls):  # type: ignore[arg-type]
        entry: dict[str, Any] = {"wire": f.metadata["wire"], "type": _type_name(hints[f.name])}
        if f.metadata["unit"]:
            entry["unit"] = f.metadata["unit"]
        if f.metadata["doc"]:
            entry["doc"] = f.metadata["doc"]
        nested = _nested_section(hints[f.name])
        if nested is not None:
            entry["fields"] = _describe(nested)["fields"]
        fields[f.name] = entry
    return {"wire": cls.WIRE, "doc": (cls.__doc__ or "").strip(), "fields": fields}


def _nested_section(tp: Any) -> type[Section] | None:
    for arg in (tp, *typing.get_args(tp)):
        if isinstance(arg, type) and issubclass(arg, Section):
            return arg
    return None
