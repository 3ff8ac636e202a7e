"""What the MAVLink vehicle exchanges with the platform: the :class:`Request` s a ground
station makes (the platform decides them), the NavCam as announced (:class:`CameraInfo`) and
what the telemetry reports (:class:`VehicleState`). Plain data, no protocol.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas.messages import Attitude, ControllerStatus, GpsFix, PoseEstimate
from platformd.mavlink.missions import MissionItem
from platformd.mavlink.modes import FlightMode

Peer = tuple[str, int]
"""A ground station's address."""
Origin = tuple[Peer, int, int, bool]
"""Who sent a message: (address, system, component, signed)."""


class Severity:
    EMERGENCY = mavlink.MAV_SEVERITY_EMERGENCY
    CRITICAL = mavlink.MAV_SEVERITY_CRITICAL
    ERROR = mavlink.MAV_SEVERITY_ERROR
    WARNING = mavlink.MAV_SEVERITY_WARNING
    NOTICE = mavlink.MAV_SEVERITY_NOTICE
    INFO = mavlink.MAV_SEVERITY_INFO


# --------------------------------------------------------------------------- requests

SAFETY_COMMANDS = (mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_DO_FLIGHTTERMINATION)
"""Arm, disarm, terminate: platformd.mavlink.arming (issue 27)."""


@dataclass(frozen=True)
class Request:
    """Something a ground station asked that changes the robot: the platform decides."""

    peer: Peer
    system: int
    component: int
    signed: bool


@dataclass(frozen=True)
class SetMode(Request):
    mode: FlightMode
    command: int
    """What the COMMAND_ACK names: MAV_CMD_DO_SET_MODE, MAV_CMD_MISSION_START, or SET_MODE's
    message id (ArduPilot's convention)."""


@dataclass(frozen=True)
class UploadItems(Request):
    """A whole mission or fence arrived (or a MISSION_CLEAR_ALL: no items)."""

    mission_type: int
    items: tuple[MissionItem, ...]


@dataclass(frozen=True)
class GoTo(Request):
    """GUIDED: drive to (latitude, longitude) and stop (DO_REPOSITION, or
    SET_POSITION_TARGET_GLOBAL_INT with ``command`` None: no COMMAND_ACK)."""

    latitude: float
    longitude: float
    command: int | None


@dataclass(frozen=True)
class SetCurrent(Request):
    """MISSION_SET_CURRENT or MAV_CMD_DO_SET_MISSION_CURRENT: the patrol's next waypoint."""

    seq: int
    """The mission item (1: the first waypoint; 0 is home)."""
    command: int | None
    """MAV_CMD_DO_SET_MISSION_CURRENT when asked by command (a COMMAND_ACK answers), None
    for the message (MISSION_CURRENT answers, a STATUSTEXT says a refusal)."""


@dataclass(frozen=True)
class ManualInput(Request):
    """MANUAL_CONTROL as a velocity: linear forward, angular to the left, each in [-1, 1]."""

    linear: float
    angular: float


@dataclass(frozen=True)
class StartVideo(Request):
    """A ground station asked for the NavCam's stream (sent to its own address)."""


# --------------------------------------------------------------------------- state


@dataclass
class CameraInfo:
    """The NavCam as the camera component announces it."""

    width: int
    height: int
    framerate: float
    bitrate_kbps: int
    port: int
    framerate_now: Callable[[], float] | None = None
    """What is really sent now (the NavCam's idle/engaged rate), if known."""


@dataclass
class VehicleState:
    """What the telemetry reports; the service keeps it current from the bus."""

    fix: GpsFix | None = None
    pose: PoseEstimate | None = None
    attitude: Attitude | None = None
    controller: ControllerStatus | None = None
    imu_ok: bool | None = None
    gps_present: bool = False
    motor_present: bool = False
    """A motor controller is fitted: its bit is present, healthy once it has answered."""
    mode: FlightMode = FlightMode.HOLD
    failsafe: bool = False
    armed: bool = True
    """The heartbeat's SAFETY_ARMED flag (platformd.arming; armed without it)."""
    prearm_ok: bool | None = None
    """SYS_STATUS's pre-arm check bit: the pre-arm checks pass (None: not reported)."""
    throttle: float = 0.0
    waypoint: int | None = None
    """The patrol's target (route index), None when idle."""
    waypoints: int = 0
    waypoint_seqs: tuple[int, ...] = ()
    """The mission item of each route waypoint, when an uploaded mission is the route (its
    speed items and a home-less first item shift the numbering); empty: index + 1."""
    home: tuple[float, float, float] | None = None
    inside_fence: bool | None = None
    """The robot inside the map's boundary and out of its keep-outs; None without a map."""
    params: list[tuple[str, float, int]] = field(default_factory=list)
    """(name ≤ 16 characters, value, MAV_PARAM_TYPE)."""
