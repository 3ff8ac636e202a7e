"""Bus message types: small frozen dataclasses. Topics are in :mod:`brasidas.topics`."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum, StrEnum
from time import monotonic
from typing import Any

from brasidas.codecs.commands import CommandCode
from brasidas.codecs.telemetry_schema import Snapshot
from brasidas.status import Battery


@dataclass(frozen=True)
class CommandResult:
    """A subsystem's answer to a system command (platformd.commands routes them)."""

    accepted: bool
    reason: str = ""
    result: Any = None

    def as_dict(self) -> dict[str, Any]:
        return {"accepted": self.accepted, "reason": self.reason, "result": self.result}


class Mode(Enum):
    AUTONOMOUS = "autonomous"
    TELEOP = "teleop"


@dataclass(frozen=True)
class OverrideState:
    """Manual override (MOVRD) state and who holds it."""

    engaged: bool
    session_id: str | None = None
    station_id: str | None = None

    @property
    def mode(self) -> Mode:
        return Mode.TELEOP if self.engaged else Mode.AUTONOMOUS


@dataclass(frozen=True)
class ControlState:
    """Which session holds control of the platform (command authority), and how it changed."""

    session_id: str | None = None
    station_id: str | None = None
    previous_station_id: str | None = None
    """The station that held control before, when it was taken from it or lost."""
    reason: str = ""


@dataclass(frozen=True)
class ArmingState:
    """Armed (motors may move) or disarmed (held at zero), and why it changed (issue 27)."""

    armed: bool
    reason: str = ""


@dataclass(frozen=True)
class SafetyNotice:
    """A safety announcement for ground stations and logs: pre-arm reasons, the autostart
    countdown, who stopped the robot. ``severity`` is a MAVLink severity (0-7)."""

    severity: int
    text: str


class FailsafeStep(Enum):
    """The failsafe ladder's step (platformd.failsafe)."""

    NORMAL = "normal"
    HOLD = "hold"
    """The override holder went silent: motors zero, payload safe, velocities dropped."""
    RELEASED = "released"
    """Silent past ``failsafe.release_after`` with action release: the override went."""


@dataclass(frozen=True)
class FailsafeState:
    step: FailsafeStep = FailsafeStep.NORMAL
    station_id: str | None = None
    reason: str = ""


@dataclass(frozen=True)
class SpeedCap:
    """The teleop speed limit for the measured latency (platformd.speedcap)."""

    fraction: float = 1.0
    """Of the platform's maximum speed: teleop velocities are clamped to ±this."""
    cap_kmh: float = 0.0
    video_ms: float | None = None
    command_ms: float | None = None
    reason: str = ""


@dataclass(frozen=True)
class SessionOpened:
    session_id: str
    station_id: str
    peer_host: str


@dataclass(frozen=True)
class SessionClosed:
    session_id: str
    station_id: str
    reason: str
    """"disconnect", "timeout" or "shutdown"."""


@dataclass(frozen=True)
class LightsState:
    main: bool = False
    positional: bool = False
    errors: dict[str, str] = field(default_factory=dict)
    """Why a light cannot be switched (its GPIO chip missing, its line busy), by light."""


@dataclass(frozen=True)
class Position:
    """A geographic position in degrees (WGS-84)."""

    latitude: float
    longitude: float


@dataclass(frozen=True)
class PlatformSighting:
    """Station side: a platform discovered or lost (from its beacons)."""

    platform_id: str
    signaling_url: str
    address: str


@dataclass(frozen=True)
class TelemetrySnapshot:
    """Station side: a platform's telemetry as its link holds it after an accepted datagram
    (the one read model adapters project; stationd.telemetry)."""

    platform_id: str
    snapshot: Snapshot
    time_ns: int
    """Wall clock when it arrived."""


@dataclass(frozen=True)
class PlatformLink:
    """Station side: a session with a platform opened or ended (stationd.connections).
    The connection itself is ``ctx.connections[platform_id]`` while its session is open."""

    platform_id: str
    session_id: str
    reason: str = ""
    """Why it ended (PLATFORM_DISCONNECTED only)."""


@dataclass(frozen=True)
class Velocity:
    """Platform-agnostic velocity: linear x and angular z, each in [-1, 1] (R-2.2)."""

    linear: float
    angular: float


# --------------------------------------------------------------------------- velocity stream and teleop (issue 3)


@dataclass(frozen=True)
class VelocityLinkStats:
    """The velocity receiver's counters: datagrams accepted, and dropped by reason (telemetry)."""

    accepted: int
    dropped: dict[str, int]
    """By :class:`brasidas.codecs.pvel.DropReason` value; every reason present, zeros included."""
    last_count: int | None
    """Count of the last accepted sentence."""
    age_ms: float | None = None
    """The last accepted sentence's age on arrival (ms), when it carried its send time."""
    age_max_ms: float | None = None
    """The oldest accepted sentence of the last second (ms): the speed cap's input."""


@dataclass(frozen=True)
class CommandAge:
    """The measured age of the override holder's velocity commands on arrival (ms): the
    oldest of the last second (the speed cap's command latency), and the latest."""

    max_ms: float
    last_ms: float
    samples: int


@dataclass(frozen=True)
class MotionState:
    """Which source drives the motors, and whether the teleop deadman holds them at zero."""

    mode: Mode
    deadman: bool
    """In teleop: no valid velocity for ``velocity.deadman`` seconds, motors held at zero."""
    command: Velocity
    """The last motor command published."""


@dataclass(frozen=True)
class ControllerStatus:
    """The motor controller driver's view of the AX3500 (platformd.motor): on every change
    of connection and after every status poll."""

    connected: bool
    battery_volts: float | None = None
    battery_monitor: bool = True
    """Command 20.4: the coarse battery level is reported (telemetry and beacon)."""
    heatsink_c: tuple[float, float] | None = None
    motor_amps: tuple[float, float] | None = None
    internal_volts: float | None = None
    error: str = ""
    """Why it is not driving (port missing, controller silent, wrong mode), else empty."""
    stamp: float = field(default_factory=monotonic, compare=False, repr=False, kw_only=True)
    """When the polled readings were taken (``time.monotonic()``): telemetry shows their age."""


# --------------------------------------------------------------------------- telemetry (issue 4)


@dataclass(frozen=True)
class PlatformHealth:
    """A coarse summary of the platform for the beacon's status word (platformd.telemetry)."""

    battery: Battery
    """The coarse level (UNKNOWN when the monitor is off)."""
    gps_fix: bool
    streaming: bool
    """At least one media stream is sending."""
    controller: bool
    """The motor controller answers."""
    fault: bool
    faults: tuple[str, ...] = ()
    """What is wrong, e.g. ("controller", "stream:navcam")."""


@dataclass(frozen=True)
class StationNotification:
    """A station-side notification (command group 90): a warning raised or cleared."""

    code: CommandCode
    platform_id: str
    name: str
    """Stable warning name, e.g. "low_battery" or "stream_failed:navcam"."""
    active: bool
    """True when raised, False when cleared."""
    message: str
    time: float
    """Station wall clock (seconds since the epoch)."""

    def as_dict(self) -> dict[str, Any]:
        return {
            "code": str(self.code),
            "platform_id": self.platform_id,
            "name": self.name,
            "active": self.active,
            "message": self.message,
            "time": self.time,
        }


# --------------------------------------------------------------------------- media (issue 5)


@dataclass(frozen=True)
class StreamStatus:
    """One media stream's state (brasidas.media): published on every change."""

    name: str
    """Stream name, e.g. "navcam"."""
    kind: str
    """"video_out", "audio_out", "audio_in" or "payload_camera"."""
    state: str
    """"idle", "playing", "paused" or "failed"."""
    reason: str = ""
    """Why it failed (readable), empty otherwise."""
    destination: str = ""
    """Where it is sent ("host:port") or where it listens; empty when idle."""

    def as_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "kind": self.kind,
            "state": self.state,
            "reason": self.reason,
            "destination": self.destination,
        }


# --------------------------------------------------------------------------- sensors (issue 4)


@dataclass(frozen=True)
class GpsFix:
    """One epoch's fix from the GPS receiver (platformd.gps)."""

    latitude: float
    longitude: float
    altitude_m: float | None
    """Above mean sea level (GGA); None when the epoch had no GGA."""
    speed_mps: float | None
    course_deg: float | None
    """Course over ground, clockwise from true north."""
    quality: int
    """GGA fix quality: 1 GPS, 2 DGPS, 4/5 RTK, 6 dead reckoning."""
    satellites: int | None
    hdop: float | None
    time: str
    """UTC, ISO 8601 ("2017-01-10T00:09:41.000Z"; time of day only until a date is known)."""
    stamp: float = field(default_factory=monotonic, compare=False, repr=False, kw_only=True)
    """When the reading was taken (``time.monotonic()``): telemetry reports its age from it."""


@dataclass(frozen=True)
class GpsFixLost:
    """The fix went away: the receiver reports none, fell silent, or its port vanished."""

    reason: str
    last_fix_time: str | None = None


@dataclass(frozen=True)
class GpsStats:
    """The GPS reader's counters (at most once a second, when they changed)."""

    connected: bool
    port: str
    sentences: int
    by_type: dict[str, int]
    dropped: dict[str, int]
    """By :class:`brasidas.codecs.nmea.DropReason` value: checksum, malformed, unknown, noise."""
    fixes: int
    incomplete_epochs: int
    error: str = ""


@dataclass(frozen=True)
class Attitude:
    """Orientation from the IMU's Madgwick filter (platformd.imu): body to world (ENU)."""

    w: float
    x: float
    y: float
    z: float
    roll_deg: float
    pitch_deg: float
    yaw_deg: float
    """Counter-clockwise about z-up from the start orientation (no magnetometer: it drifts)."""
    stamp: float = field(default_factory=monotonic, compare=False, repr=False, kw_only=True)
    """When the reading was taken (``time.monotonic()``): telemetry reports its age from it."""


@dataclass(frozen=True)
class ImuStatus:
    """The IMU driver's health, about once a second."""

    ok: bool
    error: str = ""
    """Why it is not reading: no device on the bus, wrong WHO_AM_I, read errors."""
    temperature_c: float | None = None
    samples: int = 0
    read_errors: int = 0
    calibrated: bool = False
    """The gyro's zero-rate offset was measured (the first still second after start)."""
    fifo_overflows: int = 0
    """FIFO overflows (samples lost, FIFO reset) since start."""


# --------------------------------------------------------------------------- autonomy (issue 12)


@dataclass(frozen=True)
class PoseEstimate:
    """Where the robot is, from localization (today GPS + IMU + commanded motion; SLAM later)."""

    time: float
    """Monotonic clock of the platform (seconds) the pose is for."""
    latitude: float
    longitude: float
    x_m: float
    """East of ``origin`` (metres, the localization's local frame)."""
    y_m: float
    """North of ``origin``."""
    origin: tuple[float, float]
    """(latitude, longitude) of the local frame's origin."""
    yaw_rad: float
    """Counter-clockwise from east."""
    speed_mps: float
    sigma_xy_m: float
    """Position uncertainty (one standard deviation, the larger axis)."""
    sigma_heading_deg: float
    heading_known: bool
    """False until the robot has moved enough for a course over ground (no magnetometer)."""
    fix_age_s: float | None
    """Seconds since the last GPS fix at ``time``; None: never had one."""
    source: str = "gps+imu"

    @property
    def heading_deg(self) -> float:
        """Compass heading, clockwise from north, [0, 360)."""
        return (90.0 - math.degrees(self.yaw_rad)) % 360.0


class PatrolState(StrEnum):
    IDLE = "idle"
    """Nothing to do: no map or no waypoints."""
    PATROLLING = "patrolling"
    SUSPENDED = "suspended"
    """The operator holds the manual override; resumes when released."""
    HOLDING = "holding"
    """Stopped for safety (``reason``); resumes when the cause clears."""
    STOPPED = "stopped"
    """Stopped by the operator, a map reload or a route with nothing reachable."""


@dataclass(frozen=True)
class PatrolStatus:
    """The patrol's state (``PATROL_STATUS``): what ``get_patrol``, telemetry and the CLI show."""

    state: PatrolState
    enabled: bool
    """The patrol automation is switched on (command 10.8)."""
    waypoint: int | None
    """Index in the route of the current target."""
    distance_m: float | None
    """Along the planned path to the target."""
    lap: int
    reason: str
    """Why it is not patrolling (holding, stopped, idle), or what it is doing."""
    waypoints: int
    path: tuple[tuple[float, float], ...] = field(default=())
    """The planned path as (latitude, longitude) points; empty when none."""

    def as_dict(self) -> dict[str, Any]:
        return {
            "state": self.state.value,
            "enabled": self.enabled,
            "waypoint": self.waypoint,
            "distance_m": self.distance_m,
            "lap": self.lap,
            "reason": self.reason,
            "waypoints": self.waypoints,
            "path": [[round(lat, 7), round(lon, 7)] for lat, lon in self.path],
        }


@dataclass(frozen=True)
class Automations:
    """Which onboard automations are switched on (R-3), by name: patrol, auto_framerate,
    stream_retries, battery_monitor, diagnostics (each owner reports its own)."""

    switches: tuple[tuple[str, bool], ...] = ()

    def as_dict(self) -> dict[str, bool]:
        return dict(self.switches)


# --------------------------------------------------------------------------- recorder (issue 23)


@dataclass(frozen=True)
class CommandReceived:
    """A command a station sent (a system command, or a control method such as a route or a
    map) and the answer it got, with who sent it: what the recorder keeps."""

    kind: str
    """"system" (a command code) or "rpc" (a control method)."""
    name: str
    """The code ("10.4") or the method ("set_waypoints")."""
    payload: str
    """The payload, or the method's parameters as JSON (cut at 4 KiB)."""
    session_id: str | None
    station_id: str | None
    accepted: bool
    reason: str = ""


@dataclass(frozen=True)
class CommandSent:
    """Station side: a system command this station sent a platform for its operator, with the
    answer (stationd.connections): what Foxglove's live ``/commands`` shows."""

    platform_id: str
    command: CommandReceived
