"""The MAVLink 2 vehicle, sans-IO: datagrams in, datagrams and requests out.

:class:`MavlinkVehicle` keeps one :class:`Link` per ground station address (the configured
targets, and whoever talks to it). ``feed(data, peer, now)`` parses a datagram with pymavlink,
checks its signature, answers what needs no decision (telemetry requests, parameters, MAVFTP's
NAK, mission downloads, the upload's item-by-item requests) and returns the
:class:`Request` s the platform must decide: modes, mission and fence uploads, the joystick.
The platform answers each with :meth:`answer_command` or :meth:`answer_upload`.
``tick(now)`` sends the telemetry that is due and re-requests lost mission items. What it sends
is in :attr:`outbox` until :meth:`take` empties it. No sockets, no clock: the transport and the
service (platformd.mavlink.service) do that.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas.admission import SourceLedger
from brasidas.messages import Attitude, ControllerStatus, GpsFix, PoseEstimate
from platformd.mavlink import ftp, guided, manual, missions, modes, protocol_version
from platformd.mavlink.missions import FENCE, MAX_ITEMS, MISSION, RALLY, MissionItem, command_name
from platformd.mavlink.modes import FlightMode
from platformd.mavlink.signing import SignatureCheck, SigningClock, Verdict

_LOGGER = logging.getLogger(__name__)

Peer = tuple[str, int]

UPLOAD_RETRY_S = 0.25
"""A mission item not arrived this long after its request is asked for again."""
UPLOAD_RETRIES = 8
"""Requests of one item before the upload is abandoned."""
STATUSTEXT_CHUNK = 50
"""MAVFTP's "unknown command": the client falls back (MAVProxy to PARAM_REQUEST_LIST)."""
NO_HOLDER = 0
MAX_LINKS = 32
"""Ground station addresses kept at once: a flood from made-up source addresses costs a
bounded table (the configured targets are always kept)."""
STRANGER_LINKS = 16
"""Of those, at most this many strangers: a trusted ground station always finds a slot."""


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


@dataclass
class _Upload:
    mission_type: int
    count: int
    items: dict[int, MissionItem] = field(default_factory=dict)
    asked: dict[int, float] = field(default_factory=dict)
    """Items requested and not arrived: when each was last asked for."""
    retries: dict[int, int] = field(default_factory=dict)
    waiting: bool = False
    """All items in: the platform's verdict is awaited."""

    def missing(self) -> list[int]:
        return [seq for seq in range(self.count) if seq not in self.items]


@dataclass
class Link:
    """One ground station address: its parser, encoder, signing check and transfers."""

    peer: Peer
    decoder: Any
    encoder: Any
    configured: bool
    last_heard: float = -math.inf
    last_trusted: float = -math.inf
    """The last message that could command the robot (signed, or unsigned control allowed):
    only those keep a ground station's session, and the failsafe ladder, alive."""
    gcs_system: int = 0
    check: SignatureCheck | None = None
    upload: _Upload | None = None
    upload_owner: tuple[int, int] = (0, 0)
    last_ack: tuple[int, int] | None = None
    """(mission_type, result) of the last upload, resent if the station repeats its last item."""

    @property
    def stranger(self) -> bool:
        """Not a configured target and never trusted (signed, or unsigned control allowed):
        its source address may be anyone's, so it gets no more than it gives."""
        return not self.configured and self.last_trusted == -math.inf


# --------------------------------------------------------------------------- the vehicle


class MavlinkVehicle:
    """One MAVLink vehicle (component 1) with its camera (component 100)."""

    def __init__(
        self,
        system_id: int,
        *,
        targets: tuple[Peer, ...] = (),
        key: bytes | None = None,
        allow_unsigned_control: bool = False,
        link_timeout: float = 10.0,
        upload_window: int = 1,
        rates: tuple[float, float, float] = (1.0, 5.0, 1.0),
        camera: CameraInfo | None = None,
        wall_clock: Callable[[], float] | None = None,
        mission_items: Callable[[int], list[MissionItem]] = lambda mission_type: [],
        ledger: SourceLedger | None = None,
    ) -> None:
        self.system_id = system_id
        self.ledger = ledger if ledger is not None else SourceLedger()
        """Bytes sent on each source address's behalf (brasidas.admission): the platform's."""
        self._now = 0.0
        self.key = key
        self.allow_unsigned_control = allow_unsigned_control
        self.safety_request: Callable[..., list[Request]] | None = None
        """Arm, disarm, terminate (:data:`SAFETY_COMMANDS`): platformd.mavlink.arming's
        ``safety_request``, set by the service; unsupported without it."""
        self.link_timeout = link_timeout
        self.upload_window = upload_window
        """Mission items requested ahead during an upload (1: strictly one at a time)."""
        self.heartbeat_hz, self.position_hz, self.status_hz = rates
        self.camera = camera
        self.signing_clock = SigningClock(wall_clock)
        self.signatures = SignatureCheck(key, self.signing_clock) if key is not None else None
        """One replay table for the vehicle: every link's signed frames go through it."""
        self.mission_items = mission_items
        self._components = {None, 0, modes.VEHICLE_COMPONENT}
        """Target components answered: the vehicle's, the camera's, and broadcasts."""
        if camera is not None:
            self._components.add(modes.CAMERA_COMPONENT)
        """The stored mission (MISSION) or fence (FENCE) as items, for downloads."""
        self.state = VehicleState()
        self.links: dict[Peer, Link] = {}
        self.outbox: list[tuple[bytes, Peer]] = []
        self.counters: dict[str, int] = dict.fromkeys(
            (
                "received",
                "bad_frames",
                "unsigned",
                "signed",
                "bad_signature",
                "replayed",
                "not_for_us",
                "refused_unsigned",
                "links_forgotten",
                "handler_errors",
                "links_refused",
                "setup_signing_refused",
                "stranger_frames_suppressed",
                "stranger_bytes_suppressed",
                "video_refused",
            ),
            0,
        )
        self._due: dict[str, float] = {}
        self._statustext_id = 0
        self._boot: float | None = None
        for peer in targets:
            self._link(peer, configured=True)

    # ------------------------------------------------------------------ input

    def feed(self, data: bytes, peer: Peer, now: float) -> list[Request]:
        """One datagram from ``peer``: answers go to the outbox; returns what needs deciding."""
        if self._boot is None:
            self._boot = now
        self._now = now
        link = self.links.get(peer)
        new = link is None
        if link is None:
            if not self._admit(data):
                self.counters["links_refused"] += 1
                return []
            link = self._link(peer, configured=False)
        if link.stranger:  # its credit, one per address (brasidas.admission.SourceLedger)
            self.ledger.received(peer[0], len(data), now)
        try:
            messages = link.decoder.parse_buffer(data) or []
        except Exception:  # pymavlink raises for a frame it cannot even delimit
            link.decoder.buf = bytearray()
            link.decoder.buf_index = 0
            self.counters["bad_frames"] += 1
            messages = []
        requests: list[Request] = []
        for message in messages:
            if message.get_type() == "BAD_DATA" or isinstance(message, mavlink.MAVLink_unknown):
                # pymavlink hands an unknown message id back before checking its CRC:
                # for random bytes that is noise, not a message.
                self.counters["bad_frames"] += 1
                continue
            signed = self._verdict(link, message)
            if signed is None:
                continue
            self.counters["received"] += 1
            link.last_heard = now
            if signed or self.allow_unsigned_control:
                link.last_trusted = now
            try:
                requests.extend(self._handle(link, message, signed, now))
            except Exception:  # one odd message never stops the endpoint
                self.counters["handler_errors"] += 1
                _LOGGER.exception("MAVLink: %s from %s not handled", message.get_type(), peer)
        if not link.configured and link.last_heard == -math.inf:
            del self.links[peer]  # nothing valid from a stranger: no state kept for it
        elif new and link.stranger and self._strangers() > STRANGER_LINKS:
            del self.links[peer]  # admitted for its signed flag, which did not verify
            self.counters["links_refused"] += 1
        return requests

    def _strangers(self) -> int:
        return sum(1 for link in self.links.values() if link.stranger)

    def _admit(self, data: bytes) -> bool:
        """Room for a new address: strangers share :data:`STRANGER_LINKS` slots; a datagram
        that may be signed (verified once parsed) may also take the slot of the stranger
        heard longest ago."""
        strangers = self._strangers()
        if strangers < STRANGER_LINKS and len(self.links) < MAX_LINKS:
            return True
        maybe_signed = (
            self.signatures is not None and len(data) > 2 and data[0] == 0xFD and data[2] & 1
        )
        if not maybe_signed:
            return False
        if len(self.links) >= MAX_LINKS:
            if not strangers:
                return False
            oldest = min(
                (link for link in self.links.values() if link.stranger),
                key=lambda link: link.last_heard,
            )
            del self.links[oldest.peer]
        return True

    def _verdict(self, link: Link, message: Any) -> bool | None:
        """True signed, False unsigned, None to drop (bad signature, replay)."""
        if link.check is None:
            self.counters["unsigned"] += 1
            return False
        verdict = link.check.check(message.get_msgbuf())
        if verdict is Verdict.SIGNED:
            self.counters["signed"] += 1
            return True
        if verdict is Verdict.UNSIGNED:
            self.counters["unsigned"] += 1
            return False
        self.counters["bad_signature" if verdict is Verdict.BAD_SIGNATURE else "replayed"] += 1
        return None

    def _handle(self, link: Link, message: Any, signed: bool, now: float) -> list[Request]:
        kind = message.get_type()
        system = message.get_srcSystem()
        # MANUAL_CONTROL names its vehicle in ``target``, the others in ``target_system``.
        target = getattr(message, "target_system", getattr(message, "target", None))
        component = getattr(message, "target_component", None)
        if target not in (None, 0, self.system_id) or component not in self._components:
            self.counters["not_for_us"] += 1
            return []
        handler = _HANDLERS.get(kind)
        if kind == "HEARTBEAT" and message.type == mavlink.MAV_TYPE_GCS:
            link.gcs_system = system
        if handler is None:
            return []
        origin = (link.peer, system, message.get_srcComponent(), signed)
        result: list[Request] = handler(self, link, message, origin, now)
        return result

    # ------------------------------------------------------------------ answers

    def answer_command(
        self,
        request: Request,
        result: int,
        text: str = "",
        *,
        holder_system: int = NO_HOLDER,
        command: int | None = None,
    ) -> None:
        """COMMAND_ACK for ``request`` (and a STATUSTEXT with ``text`` when refused)."""
        link = self.links.get(request.peer)
        if link is None:
            return
        if command is None:
            asked = request.command if isinstance(request, SetMode | SetCurrent | GoTo) else None
            command = asked or 0
        self._send(
            link,
            mavlink.MAVLink_command_ack_message(
                command, result, 0, holder_system, request.system, request.component
            ),
        )
        if text:
            severity = Severity.INFO if result == mavlink.MAV_RESULT_ACCEPTED else Severity.WARNING
            self._statustext_to(link, severity, text)

    def answer_upload(self, request: UploadItems, result: int, text: str = "") -> None:
        """MISSION_ACK for an upload (a STATUSTEXT with ``text``: the reason of a refusal)."""
        link = self.links.get(request.peer)
        if link is None:
            return
        if link.upload is not None and link.upload.waiting:
            link.upload = None  # not a newer upload the station started meanwhile
        link.last_ack = (request.mission_type, result)
        self._mission_ack(link, request.system, request.component, result, request.mission_type)
        if text:
            severity = Severity.INFO if result == mavlink.MAV_MISSION_ACCEPTED else Severity.WARNING
            self._statustext_to(link, severity, text)

    def answer_set_current(
        self, request: SetCurrent, result: int, text: str = "", *, holder_system: int = NO_HOLDER
    ) -> None:
        """The answer to a new current item: a COMMAND_ACK when asked by command; accepted,
        MISSION_CURRENT with it at once (the mission protocol's answer); refused, the reason."""
        link = self.links.get(request.peer)
        if link is None:
            return
        accepted = result == mavlink.MAV_RESULT_ACCEPTED
        if request.command is not None:
            self.answer_command(request, result, text, holder_system=holder_system)
        elif text:
            self._statustext_to(link, Severity.INFO if accepted else Severity.WARNING, text)
        if accepted:
            self.state.waypoint = missions.route_index(self.state.waypoint_seqs, request.seq)
            self._send(link, self._mission_current())

    def statustext(self, severity: int, text: str) -> None:
        """A warning (or notice) for every ground station (group 90's annunciations)."""
        for link in self.links.values():
            self._statustext_to(link, severity, text)

    def take(self) -> list[tuple[bytes, Peer]]:
        """Empty the outbox."""
        out, self.outbox = self.outbox, []
        return out

    # ------------------------------------------------------------------ time

    def tick(self, now: float) -> None:
        """Telemetry that is due, mission item re-requests, forgotten links."""
        if self._boot is None:
            self._boot = now
        self._now = now
        for peer, link in list(self.links.items()):
            if not link.configured and now - link.last_heard > self.link_timeout:
                del self.links[peer]
                self.counters["links_forgotten"] += 1
                continue
            self._retry_upload(link, now)
        if self._due_now("heartbeat", self.heartbeat_hz, now):
            self._broadcast(self._heartbeat())
            if self.camera is not None:
                self._broadcast(self._camera_heartbeat(), modes.CAMERA_COMPONENT)
        if self._due_now("position", self.position_hz, now):
            for message in self._position_messages(now):
                self._broadcast(message)
        if self._due_now("status", self.status_hz, now):
            for message in self._status_messages():
                self._broadcast(message)
        if self._due_now("home", self.status_hz / 5, now):
            home = self._home_position()
            if home is not None:
                self._broadcast(home)

    def _due_now(self, name: str, rate_hz: float, now: float) -> bool:
        due = self._due.get(name, now)
        if now < due:
            return False
        period = 1.0 / rate_hz
        # Catch up at most one period: a stalled loop does not burst old telemetry.
        self._due[name] = max(due + period, now + period * 0.5)
        return True

    # ------------------------------------------------------------------ telemetry

    def _heartbeat(self) -> Any:
        state = self.state
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
        if state.armed:
            base |= mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        if state.mode is FlightMode.MANUAL:
            base |= mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED
        elif state.mode is FlightMode.AUTO:
            base |= mavlink.MAV_MODE_FLAG_AUTO_ENABLED | mavlink.MAV_MODE_FLAG_GUIDED_ENABLED
        status = mavlink.MAV_STATE_CRITICAL if state.failsafe else mavlink.MAV_STATE_ACTIVE
        return mavlink.MAVLink_heartbeat_message(
            modes.VEHICLE_TYPE, modes.AUTOPILOT, base, int(state.mode), status, 3
        )

    def _camera_heartbeat(self) -> Any:
        return mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_CAMERA,
            mavlink.MAV_AUTOPILOT_INVALID,
            0,
            0,
            mavlink.MAV_STATE_ACTIVE,
            3,
        )

    def _position_messages(self, now: float) -> list[Any]:
        state = self.state
        boot_ms = self._boot_ms(now)
        out: list[Any] = []
        fix = state.fix
        if fix is not None:
            fix_type = _FIX_TYPES.get(fix.quality, mavlink.GPS_FIX_TYPE_3D_FIX)
            hdop = round(fix.hdop * 100) if fix.hdop is not None else 65535
            speed = round((fix.speed_mps or 0.0) * 100)
            course = round((fix.course_deg or 0.0) * 100) % 36000
            out.append(
                mavlink.MAVLink_gps_raw_int_message(
                    0,
                    fix_type,
                    _e7(fix.latitude),
                    _e7(fix.longitude),
                    round((fix.altitude_m or 0.0) * 1000),
                    min(hdop, 65535),
                    65535,
                    speed,
                    course,
                    fix.satellites if fix.satellites is not None else 255,
                )
            )
        elif state.gps_present:
            out.append(
                mavlink.MAVLink_gps_raw_int_message(
                    0, mavlink.GPS_FIX_TYPE_NO_FIX, 0, 0, 0, 65535, 65535, 0, 0, 255
                )
            )
        heading = self._heading_deg()
        pose = state.pose
        where = (
            (pose.latitude, pose.longitude, pose.speed_mps)
            if pose is not None
            else (fix.latitude, fix.longitude, fix.speed_mps or 0.0)
            if fix is not None
            else None
        )
        if where is not None:
            lat, lon, ground_speed = where
            altitude = fix.altitude_m if fix is not None and fix.altitude_m is not None else 0.0
            track = math.radians(heading if heading is not None else 0.0)
            out.append(
                mavlink.MAVLink_global_position_int_message(
                    boot_ms,
                    _e7(lat),
                    _e7(lon),
                    round(altitude * 1000),
                    0,
                    round(ground_speed * math.cos(track) * 100),
                    round(ground_speed * math.sin(track) * 100),
                    0,
                    round(heading * 100) % 36000 if heading is not None else 65535,
                )
            )
            out.append(
                mavlink.MAVLink_vfr_hud_message(
                    ground_speed,
                    ground_speed,
                    round(heading or 0.0) % 360,
                    round(abs(state.throttle) * 100),
                    altitude,
                    0.0,
                )
            )
        # Sent even without an IMU (level, the pose's heading): QGroundControl's instruments.
        attitude = state.attitude
        roll = math.radians(attitude.roll_deg) if attitude is not None else 0.0
        pitch = math.radians(attitude.pitch_deg) if attitude is not None else 0.0
        yaw = math.radians(heading or 0.0)
        yaw = math.atan2(math.sin(yaw), math.cos(yaw))
        out.append(mavlink.MAVLink_attitude_message(boot_ms, roll, pitch, yaw, 0.0, 0.0, 0.0))
        return out

    def _heading_deg(self) -> float | None:
        pose = self.state.pose
        if pose is not None and pose.heading_known:
            return pose.heading_deg
        attitude = self.state.attitude
        if attitude is not None:
            return (90.0 - attitude.yaw_deg) % 360.0  # the IMU's yaw is ENU's, from east
        return None

    def _status_messages(self) -> list[Any]:
        state = self.state
        sensors = _Sensors()
        sensors.add(mavlink.MAV_SYS_STATUS_SENSOR_GPS, state.gps_present, state.fix is not None)
        if state.imu_ok is not None:
            for bit in (
                mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO,
                mavlink.MAV_SYS_STATUS_SENSOR_3D_ACCEL,
            ):
                sensors.add(bit, True, state.imu_ok)
            # No compass: the bit stands for the heading source (the IMU fused with GPS
            # course), which ground stations (MAVSDK's health) require before arming.
            heading = self._heading_deg() is not None
            sensors.add(mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG, True, state.imu_ok and heading)
        if state.inside_fence is not None:
            sensors.add(mavlink.MAV_SYS_STATUS_GEOFENCE, True, state.inside_fence)
        if state.prearm_ok is not None:  # "always healthy when armed" (MAVLink's definition)
            sensors.add(mavlink.MAV_SYS_STATUS_PREARM_CHECK, True, state.prearm_ok or state.armed)
        controller = state.controller
        if controller is not None:
            sensors.add(mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS, True, controller.connected)
            sensors.add(
                mavlink.MAV_SYS_STATUS_SENSOR_BATTERY,
                controller.battery_volts is not None,
                controller.battery_volts is not None and not controller.error,
            )
        volts = controller.battery_volts if controller is not None else None
        millivolts = round(volts * 1000) if volts is not None else 65535
        out: list[Any] = [
            mavlink.MAVLink_sys_status_message(
                sensors.present,
                sensors.present,
                sensors.health,
                0,
                millivolts,
                -1,
                -1,
                0,
                0,
                0,
                0,
                0,
                0,
            )
        ]
        if volts is not None:
            cells = [millivolts] + [65535] * 9
            out.append(
                mavlink.MAVLink_battery_status_message(
                    0,
                    mavlink.MAV_BATTERY_FUNCTION_ALL,
                    mavlink.MAV_BATTERY_TYPE_UNKNOWN,  # lead-acid has no MAV_BATTERY_TYPE
                    32767,
                    cells,
                    -1,
                    -1,
                    -1,
                    -1,
                )
            )
        out.append(self._mission_current())
        return out

    def _mission_current(self) -> Any:
        """The patrol's target as a mission item (route index + 1: item 0 is home)."""
        state = self.state
        seqs = state.waypoint_seqs
        if state.waypoint is None:
            seq = 0
        elif state.waypoint < len(seqs):
            seq = seqs[state.waypoint]
        else:
            seq = state.waypoint + 1
        total = seqs[-1] + 1 if seqs else state.waypoints + 1
        return mavlink.MAVLink_mission_current_message(seq, total)

    def _home_position(self) -> Any | None:
        home = self.state.home
        if home is None:
            return None
        lat, lon, alt = home
        return mavlink.MAVLink_home_position_message(
            _e7(lat), _e7(lon), round(alt * 1000), 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0, 0, 0
        )

    def _autopilot_version(self) -> Any:
        return mavlink.MAVLink_autopilot_version_message(
            modes.CAPABILITIES,
            # Not OFFICIAL: QGroundControl compares an official version with ArduPilot's
            # latest stable release and says "not the latest stable firmware".
            0x00010000 | mavlink.FIRMWARE_VERSION_TYPE_DEV,
            0,
            0,
            0,
            [0] * 8,
            [0] * 8,
            [0] * 8,
            0,
            0,
            self.system_id,
        )

    def _boot_ms(self, now: float) -> int:
        return int((now - (self._boot or now)) * 1000) & 0xFFFFFFFF

    # ------------------------------------------------------------------ camera

    def _camera_information(self) -> Any:
        camera = self.camera
        assert camera is not None
        return mavlink.MAVLink_camera_information_message(
            0,
            _fixed(b"Brasidas", 32),
            _fixed(b"NavCam", 32),
            0,
            0.0,
            0.0,
            0.0,
            camera.width,
            camera.height,
            0,
            mavlink.CAMERA_CAP_FLAGS_HAS_VIDEO_STREAM,
            0,
            b"",
        )

    def _video_stream_information(self) -> Any:
        camera = self.camera
        assert camera is not None
        return mavlink.MAVLink_video_stream_information_message(
            1,
            1,
            mavlink.VIDEO_STREAM_TYPE_RTPUDP,
            mavlink.VIDEO_STREAM_STATUS_FLAGS_RUNNING,
            camera.framerate_now() if camera.framerate_now is not None else camera.framerate,
            camera.width,
            camera.height,
            camera.bitrate_kbps,
            0,
            0,
            b"NavCam",
            # RTP over UDP: the port alone (the spec's form; QGC reads it so).
            str(camera.port).encode(),
            mavlink.VIDEO_STREAM_ENCODING_H264,
        )

    # ------------------------------------------------------------------ handlers

    def _on_command(self, link: Link, message: Any, origin: Any, now: float) -> list[Request]:
        command = message.command
        target_component = message.target_component
        is_camera = target_component == modes.CAMERA_COMPONENT
        peer, system, component, signed = origin
        params = (message.param1, message.param2, message.param3, message.param4)
        ack = self._acker(link, command, system, component, is_camera)
        if command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            return self._request_message(link, int(params[0]), ack, origin)
        if command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            ack(mavlink.MAV_RESULT_ACCEPTED)
            self._send(link, self._autopilot_version())
            return []
        if command == mavlink.MAV_CMD_GET_HOME_POSITION:
            return self._request_message(link, mavlink.MAVLINK_MSG_ID_HOME_POSITION, ack, origin)
        if command == mavlink.MAV_CMD_REQUEST_CAMERA_INFORMATION:
            return self._request_message(
                link, mavlink.MAVLINK_MSG_ID_CAMERA_INFORMATION, ack, origin
            )
        if command == mavlink.MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION:
            return self._request_message(
                link, mavlink.MAVLINK_MSG_ID_VIDEO_STREAM_INFORMATION, ack, origin
            )
        if command in (mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_CMD_MISSION_START):
            if command == mavlink.MAV_CMD_MISSION_START:
                mode: FlightMode | None = FlightMode.AUTO
            elif not int(params[0]) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                ack(mavlink.MAV_RESULT_UNSUPPORTED, "set a custom mode: MANUAL, HOLD or AUTO")
                return []
            else:
                mode = modes.mode_named(int(params[1]))
            if mode is None:
                ack(
                    mavlink.MAV_RESULT_UNSUPPORTED,
                    f"mode {int(params[1])} is not a Brasidas mode (MANUAL, HOLD, AUTO, RTL, GUIDED)",
                )
                return []
            if not self._may_control(signed, "set mode", ack, mavlink.MAV_RESULT_DENIED):
                return []
            return [SetMode(peer, system, component, signed, mode, command)]
        if command == mavlink.MAV_CMD_DO_REPOSITION:
            target = guided.reposition_target(message)
            if target is None:
                ack(mavlink.MAV_RESULT_DENIED, "go to: no latitude, longitude in a global frame")
                return []
            if not self._may_control(signed, "go to", ack, mavlink.MAV_RESULT_DENIED):
                return []
            return [GoTo(peer, system, component, signed, *target, command)]
        if command == mavlink.MAV_CMD_DO_SET_MISSION_CURRENT:
            if not self._may_control(signed, "set current", ack, mavlink.MAV_RESULT_DENIED):
                return []
            seq = int(params[0]) if math.isfinite(params[0]) else -1
            return [SetCurrent(peer, system, component, signed, seq, command)]
        if command in SAFETY_COMMANDS and self.safety_request is not None:
            return self.safety_request(command, params, origin, ack, self._may_control)
        if command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            # Ground stations set many intervals at connect: the ACK says no, without a text
            # for each (the rates are the platform's, mavlink.*_hz).
            ack(mavlink.MAV_RESULT_DENIED)
            return []
        ack(
            mavlink.MAV_RESULT_UNSUPPORTED,
            f"command {command_name(command)} is not supported",
        )
        return []

    def _acker(
        self, link: Link, command: int, system: int, component: int, is_camera: bool
    ) -> Callable[..., None]:
        def ack(result: int, text: str = "") -> None:
            """COMMAND_ACK from the addressed component; a STATUSTEXT with ``text``."""
            self._send(
                link,
                mavlink.MAVLink_command_ack_message(command, result, 0, 0, system, component),
                modes.CAMERA_COMPONENT if is_camera else modes.VEHICLE_COMPONENT,
            )
            if text:
                self._statustext_to(link, Severity.WARNING, text)

        return ack

    def _request_message(
        self, link: Link, message_id: int, ack: Callable[..., None], origin: Any
    ) -> list[Request]:
        peer, system, component, signed = origin
        reply: Any = None
        source = modes.VEHICLE_COMPONENT
        requests: list[Request] = []
        if message_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            reply = self._autopilot_version()
        elif message_id == protocol_version.MSG_ID:
            reply = protocol_version.protocol_version()
        elif message_id == mavlink.MAVLINK_MSG_ID_HOME_POSITION:
            reply = self._home_position()
            if reply is None:
                ack(mavlink.MAV_RESULT_TEMPORARILY_REJECTED, "no home yet: waiting for a GPS fix")
                return []
        elif message_id in (
            mavlink.MAVLINK_MSG_ID_CAMERA_INFORMATION,
            mavlink.MAVLINK_MSG_ID_VIDEO_STREAM_INFORMATION,
        ):
            if self.camera is None:
                ack(mavlink.MAV_RESULT_UNSUPPORTED, "no camera on this platform")
                return []
            source = modes.CAMERA_COMPONENT
            if message_id == mavlink.MAVLINK_MSG_ID_CAMERA_INFORMATION:
                reply = self._camera_information()
            else:
                reply = self._video_stream_information()
                # Video is megabytes for a 44-byte request from an address anyone can claim:
                # only for a signed request or a configured target (issue 26, defect 2).
                if self.ledger.admits_stream(peer[0], signed or link.configured):
                    requests.append(StartVideo(peer, system, component, signed))
                else:
                    self.counters["video_refused"] += 1
                    self._statustext_to(
                        link,
                        Severity.WARNING,
                        "video: only for a signed ground station or one in mavlink.targets",
                    )
        if reply is None:
            ack(mavlink.MAV_RESULT_UNSUPPORTED)  # asked at connect for optional ones: no text
            return []
        ack(mavlink.MAV_RESULT_ACCEPTED)
        self._send(link, reply, source)
        return requests

    def _on_set_mode(self, link: Link, message: Any, origin: Any, now: float) -> list[Request]:
        peer, system, component, signed = origin
        ack = self._acker(link, mavlink.MAVLINK_MSG_ID_SET_MODE, system, component, False)
        mode = modes.mode_named(message.custom_mode)
        if mode is None or not message.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            ack(
                mavlink.MAV_RESULT_UNSUPPORTED,
                f"mode {message.custom_mode} is not a Brasidas mode (MANUAL, HOLD, AUTO, RTL, GUIDED)",
            )
            return []
        if not self._may_control(signed, "set mode", ack, mavlink.MAV_RESULT_DENIED):
            return []
        return [SetMode(peer, system, component, signed, mode, mavlink.MAVLINK_MSG_ID_SET_MODE)]

    def _may_control(
        self, signed: bool, what: str, refuse: Callable[[int, str], None], denied: int
    ) -> bool:
        """Signed, or unsigned control allowed; else ``refuse(denied, reason)``."""
        if signed or self.allow_unsigned_control:
            return True
        self.counters["refused_unsigned"] += 1
        refuse(denied, f"{what} refused: unsigned link (MAVLink signing required for control)")
        return False

    def _on_manual_control(
        self, link: Link, message: Any, origin: Any, now: float
    ) -> list[Request]:
        peer, system, component, signed = origin
        if not (signed or self.allow_unsigned_control):
            self.counters["refused_unsigned"] += 1
            return []
        linear = _axis(message.x)
        angular = -_axis(message.r)  # MAVLink's r is yaw to the right; ours turns left
        return [ManualInput(peer, system, component, signed, linear, angular)]

    def _on_position_target(
        self, link: Link, message: Any, origin: Any, now: float
    ) -> list[Request]:
        """SET_POSITION_TARGET_GLOBAL_INT: a go-to (no answer but the mode and the position)."""
        peer, system, component, signed = origin
        if message.target_system not in (0, self.system_id):
            return []
        if not (signed or self.allow_unsigned_control):
            self.counters["refused_unsigned"] += 1
            return []
        target = guided.position_target(message)
        if target is None:
            return []
        return [GoTo(peer, system, component, signed, *target, None)]

    def _on_guided_item(self, link: Link, message: Any, origin: Any) -> list[Request]:
        """A mission item with ``current`` 2 (MAVProxy's ``guided LAT LON``, ArduPilot's
        guided waypoint): a go-to; MISSION_ACK says whether it was taken."""
        peer, system, component, signed = origin

        def refuse(result: int, text: str) -> None:
            self._mission_ack(link, system, component, mavlink.MAV_MISSION_DENIED, MISSION)
            self._statustext_to(link, Severity.WARNING, text)

        target = guided.item_target(message)
        if target is None:
            refuse(0, "go to: no latitude, longitude in a global frame")
            return []
        if not self._may_control(signed, "go to", refuse, mavlink.MAV_MISSION_DENIED):
            return []
        return [GoTo(peer, system, component, signed, *target, None)]

    def _on_rc_override(self, link: Link, message: Any, origin: Any, now: float) -> list[Request]:
        """RC_CHANNELS_OVERRIDE: the joystick as ArduRover's channels (see manual.py)."""
        peer, system, component, signed = origin
        if message.target_system not in (0, self.system_id):
            return []
        if not (signed or self.allow_unsigned_control):
            self.counters["refused_unsigned"] += 1
            return []
        linear, angular = manual.rc_velocity(message)
        return [ManualInput(peer, system, component, signed, linear, angular)]

    def _on_param_request_list(
        self, link: Link, message: Any, origin: Any, now: float
    ) -> list[Request]:
        params = self.state.params
        for index in range(len(params)):
            self._send(link, self._param_value(index))
        return []

    def _on_param_request_read(
        self, link: Link, message: Any, origin: Any, now: float
    ) -> list[Request]:
        index = self._param_index(message.param_id, message.param_index)
        if index is not None:
            self._send(link, self._param_value(index))
        return []

    def _on_param_set(self, link: Link, message: Any, origin: Any, now: float) -> list[Request]:
        index = self._param_index(message.param_id, -1)
        name = _text(message.param_id)
        if index is None:
            self._statustext_to(link, Severity.WARNING, f"no parameter {name}")
            return []
        # The unchanged value tells the client the write did not take.
        self._send(link, self._param_value(index))
        self._statustext_to(
            link,
            Severity.WARNING,
            f"{name} is read-only: change it in the platform's config file",
        )
        return []

    def _param_index(self, param_id: Any, index: int) -> int | None:
        params = self.state.params
        if 0 <= index < len(params):
            return index
        name = _text(param_id)
        for position, (known, _value, _type) in enumerate(params):
            if known == name:
                return position
        return None

    def _param_value(self, index: int) -> Any:
        name, value, param_type = self.state.params[index]
        return mavlink.MAVLink_param_value_message(
            name.encode(), value, param_type, len(self.state.params), index
        )

    def _on_setup_signing(self, link: Link, message: Any, origin: Any, now: float) -> list[Request]:
        # Never from a ground station, signed or not: the key is the platform's own config.
        self.counters["setup_signing_refused"] += 1
        self._statustext_to(
            link,
            Severity.WARNING,
            "SETUP_SIGNING refused: the key is the platform's mavlink.signing_key_file",
        )
        return []

    def _on_ftp(self, link: Link, message: Any, origin: Any, now: float) -> list[Request]:
        _peer, system, component, _signed = origin
        answer = ftp.reply(bytes(message.payload))
        if answer is not None:
            self._send(
                link,
                mavlink.MAVLink_file_transfer_protocol_message(0, system, component, list(answer)),
            )
        return []

    # ------------------------------------------------------------------ missions

    def _on_mission_request_list(
        self, link: Link, message: Any, origin: Any, now: float
    ) -> list[Request]:
        _peer, system, component, _signed = origin
        mission_type = message.mission_type
        if mission_type == RALLY:
            self._send(link, mavlink.MAVLink_mission_count_message(system, component, 0, RALLY))
            return []
        if mission_type not in (MISSION, FENCE):
            self._mission_ack(
                link, system, component, mavlink.MAV_MISSION_UNSUPPORTED, mission_type
            )
            return []
        count = len(self.mission_items(mission_type))
        self._send(
            link, mavlink.MAVLink_mission_count_message(system, component, count, mission_type)
        )
        return []

    def _on_mission_request(
        self, link: Link, message: Any, origin: Any, now: float
    ) -> list[Request]:
        _peer, system, component, _signed = origin
        mission_type = message.mission_type
        items = self.mission_items(mission_type) if mission_type in (MISSION, FENCE) else []
        if not 0 <= message.seq < len(items):
            self._mission_ack(
                link, system, component, mavlink.MAV_MISSION_INVALID_SEQUENCE, mission_type
            )
            return []
        item = items[message.seq]
        # Always MISSION_ITEM_INT, even to MISSION_REQUEST: QGroundControl ignores MISSION_ITEM.
        self._send(
            link,
            mavlink.MAVLink_mission_item_int_message(
                system,
                component,
                item.seq,
                item.frame,
                item.command,
                item.current,
                item.autocontinue,
                item.param1,
                item.param2,
                item.param3,
                item.param4,
                item.x,
                item.y,
                item.z,
                mission_type,
            ),
        )
        return []

    def _on_mission_count(self, link: Link, message: Any, origin: Any, now: float) -> list[Request]:
        peer, system, component, signed = origin
        mission_type = message.mission_type
        count = message.count

        def refuse(result: int, text: str) -> None:
            self._mission_ack(link, system, component, result, mission_type)
            self._statustext_to(link, Severity.WARNING, text)

        if mission_type == RALLY and count == 0:
            self._mission_ack(link, system, component, mavlink.MAV_MISSION_ACCEPTED, RALLY)
            return []
        if mission_type not in (MISSION, FENCE):
            refuse(mavlink.MAV_MISSION_UNSUPPORTED, "rally points are not supported")
            return []
        if count > MAX_ITEMS:
            refuse(mavlink.MAV_MISSION_NO_SPACE, f"{count} items: at most {MAX_ITEMS}")
            return []
        if not self._may_control(signed, "upload", refuse, mavlink.MAV_MISSION_DENIED):
            return []
        link.upload = _Upload(mission_type, count)
        link.upload_owner = (system, component)
        link.last_ack = None
        if count == 0:
            link.upload.waiting = True
            return [UploadItems(peer, system, component, signed, mission_type, ())]
        self._request_items(link, now)
        return []

    def _on_mission_item(self, link: Link, message: Any, origin: Any, now: float) -> list[Request]:
        peer, system, component, signed = origin
        upload = link.upload
        mission_type = message.mission_type
        if message.current == guided.GUIDED_ITEM and mission_type == MISSION:
            return self._on_guided_item(link, message, origin)
        if upload is None or upload.waiting or upload.mission_type != mission_type:
            if link.last_ack is not None and link.last_ack[0] == mission_type:
                # Our ACK was lost and the station repeats its last item: repeat the ACK.
                self._mission_ack(link, system, component, link.last_ack[1], mission_type)
            return []
        if not 0 <= message.seq < upload.count or message.seq in upload.items:
            return []  # a duplicate (answering a repeated request) or out of range
        if message.get_type() == "MISSION_ITEM":
            x, y = round(message.x * 1e7), round(message.y * 1e7)
        else:
            x, y = message.x, message.y
        upload.asked.pop(message.seq, None)
        upload.items[message.seq] = MissionItem(
            message.seq,
            message.frame,
            message.command,
            message.param1,
            message.param2,
            message.param3,
            message.param4,
            x,
            y,
            message.z,
            message.autocontinue,
            message.current,
        )
        if len(upload.items) < upload.count:
            self._request_items(link, now)
            return []
        upload.waiting = True
        items = tuple(upload.items[seq] for seq in range(upload.count))
        return [UploadItems(peer, system, component, signed, mission_type, items)]

    def _on_mission_clear_all(
        self, link: Link, message: Any, origin: Any, now: float
    ) -> list[Request]:
        peer, system, component, signed = origin
        mission_type = message.mission_type

        def refuse(result: int, text: str) -> None:
            self._mission_ack(link, system, component, result, mission_type)
            self._statustext_to(link, Severity.WARNING, text)

        if mission_type not in (MISSION, FENCE):
            self._mission_ack(link, system, component, mavlink.MAV_MISSION_ACCEPTED, mission_type)
            return []
        if not self._may_control(signed, "clear", refuse, mavlink.MAV_MISSION_DENIED):
            return []
        link.upload = _Upload(mission_type, 0, waiting=True)
        return [UploadItems(peer, system, component, signed, mission_type, ())]

    def _on_mission_set_current(
        self, link: Link, message: Any, origin: Any, now: float
    ) -> list[Request]:
        peer, system, component, signed = origin

        def refuse(result: int, text: str) -> None:
            self._statustext_to(link, Severity.WARNING, text)

        if not self._may_control(signed, "set current", refuse, mavlink.MAV_RESULT_DENIED):
            return []
        return [SetCurrent(peer, system, component, signed, message.seq, None)]

    def _on_mission_ack(self, link: Link, message: Any, origin: Any, now: float) -> list[Request]:
        return []  # the end of a download: nothing kept per download

    def _request_items(self, link: Link, now: float) -> None:
        """Ask for missing items, up to ``upload_window`` outstanding at once; again for any
        asked :data:`UPLOAD_RETRY_S` ago (its request or its answer was lost)."""
        upload = link.upload
        assert upload is not None
        system, component = link.upload_owner
        for seq in upload.missing():
            asked = upload.asked.get(seq)
            if asked is not None and now - asked < UPLOAD_RETRY_S:
                continue
            if asked is None and len(upload.asked) >= self.upload_window:
                break
            if asked is not None:
                upload.retries[seq] = upload.retries.get(seq, 0) + 1
            upload.asked[seq] = now
            self._send(
                link,
                mavlink.MAVLink_mission_request_int_message(
                    system, component, seq, upload.mission_type
                ),
            )

    def _retry_upload(self, link: Link, now: float) -> None:
        upload = link.upload
        if upload is None or upload.waiting:
            return
        lost = [seq for seq, retries in upload.retries.items() if retries >= UPLOAD_RETRIES]
        if lost and now - upload.asked[lost[0]] >= UPLOAD_RETRY_S:
            system, component = link.upload_owner
            link.upload = None
            self._mission_ack(
                link,
                system,
                component,
                mavlink.MAV_MISSION_OPERATION_CANCELLED,
                upload.mission_type,
            )
            self._statustext_to(
                link, Severity.WARNING, f"upload abandoned: item {lost[0]} never came"
            )
            return
        self._request_items(link, now)

    def _mission_ack(
        self, link: Link, system: int, component: int, result: int, mission_type: int
    ) -> None:
        self._send(
            link, mavlink.MAVLink_mission_ack_message(system, component, result, mission_type)
        )

    # ------------------------------------------------------------------ sending

    def _link(self, peer: Peer, *, configured: bool) -> Link:
        decoder = mavlink.MAVLink(None, self.system_id, modes.VEHICLE_COMPONENT)
        decoder.robust_parsing = True
        encoder = mavlink.MAVLink(None, self.system_id, modes.VEHICLE_COMPONENT)
        link = Link(peer, decoder, encoder, configured)
        if self.key is not None:
            link.check = self.signatures
            encoder.signing.secret_key = self.key
            encoder.signing.sign_outgoing = True
            encoder.signing.link_id = len(self.links) & 0xFF
        self.links[peer] = link
        return link

    def broadcast(self, message: Any) -> None:
        """A message from another module (platformd.mavlink.proximity) to every link."""
        self._broadcast(message)

    def _broadcast(self, message: Any, component: int = modes.VEHICLE_COMPONENT) -> None:
        for link in self.links.values():
            if link.configured or link.last_heard > -math.inf:
                self._send(link, message, component)

    def _send(self, link: Link, message: Any, component: int = modes.VEHICLE_COMPONENT) -> None:
        self._send_all(link, [message], component)

    def _send_all(
        self, link: Link, messages: list[Any], component: int = modes.VEHICLE_COMPONENT
    ) -> None:
        """All of ``messages`` to ``link``, or, to a stranger out of credit, none (counted)."""
        encoder = link.encoder
        encoder.srcComponent = component
        if encoder.signing.sign_outgoing:
            encoder.signing.timestamp = max(encoder.signing.timestamp, self.signing_clock.now())
        first_seq = encoder.seq
        frames = []
        for message in messages:
            frames.append(message.pack(encoder))
            encoder.seq = (encoder.seq + 1) % 256
        size = sum(len(frame) for frame in frames)
        if not link.stranger:
            self.ledger.trusted_send(link.peer[0], size, "mavlink")
        elif not self.ledger.stranger_send(link.peer[0], size, self._now):
            encoder.seq = first_seq  # what it is sent shows no gap for what it was not
            self.counters["stranger_frames_suppressed"] += len(frames)
            self.counters["stranger_bytes_suppressed"] += size
            return
        self.outbox.extend((frame, link.peer) for frame in frames)

    def _statustext_to(self, link: Link, severity: int, text: str) -> None:
        data = text.encode("utf-8", "replace")[: STATUSTEXT_CHUNK * 4]
        chunks = [data[i : i + STATUSTEXT_CHUNK] for i in range(0, len(data), STATUSTEXT_CHUNK)]
        message_id = 0
        if len(chunks) > 1:
            self._statustext_id = self._statustext_id % 0xFFFF + 1
            message_id = self._statustext_id
            if len(chunks[-1]) == STATUSTEXT_CHUNK:
                chunks.append(b"")  # a full last chunk: an empty one ends the text
        self._send_all(
            link,
            [
                mavlink.MAVLink_statustext_message(severity, chunk, message_id, index)
                for index, chunk in enumerate(chunks)
            ],
        )


_Handler = Callable[[MavlinkVehicle, Link, Any, Any, float], list[Request]]

_HANDLERS: dict[str, _Handler] = {
    "COMMAND_LONG": MavlinkVehicle._on_command,
    "COMMAND_INT": MavlinkVehicle._on_command,
    "SET_MODE": MavlinkVehicle._on_set_mode,
    "MANUAL_CONTROL": MavlinkVehicle._on_manual_control,
    "RC_CHANNELS_OVERRIDE": MavlinkVehicle._on_rc_override,
    "SET_POSITION_TARGET_GLOBAL_INT": MavlinkVehicle._on_position_target,
    "PARAM_REQUEST_LIST": MavlinkVehicle._on_param_request_list,
    "PARAM_REQUEST_READ": MavlinkVehicle._on_param_request_read,
    "PARAM_SET": MavlinkVehicle._on_param_set,
    "FILE_TRANSFER_PROTOCOL": MavlinkVehicle._on_ftp,
    "SETUP_SIGNING": MavlinkVehicle._on_setup_signing,
    "MISSION_REQUEST_LIST": MavlinkVehicle._on_mission_request_list,
    "MISSION_REQUEST_INT": MavlinkVehicle._on_mission_request,
    "MISSION_REQUEST": MavlinkVehicle._on_mission_request,
    "MISSION_COUNT": MavlinkVehicle._on_mission_count,
    "MISSION_ITEM_INT": MavlinkVehicle._on_mission_item,
    "MISSION_ITEM": MavlinkVehicle._on_mission_item,
    "MISSION_CLEAR_ALL": MavlinkVehicle._on_mission_clear_all,
    "MISSION_SET_CURRENT": MavlinkVehicle._on_mission_set_current,
    "MISSION_ACK": MavlinkVehicle._on_mission_ack,
}

_FIX_TYPES = {
    0: mavlink.GPS_FIX_TYPE_NO_FIX,
    1: mavlink.GPS_FIX_TYPE_3D_FIX,
    2: mavlink.GPS_FIX_TYPE_DGPS,
    4: mavlink.GPS_FIX_TYPE_RTK_FIXED,
    5: mavlink.GPS_FIX_TYPE_RTK_FLOAT,
}
"""NMEA GGA quality → GPS_FIX_TYPE."""


class _Sensors:
    def __init__(self) -> None:
        self.present = 0
        self.health = 0

    def add(self, bit: int, present: bool, healthy: bool) -> None:
        if present:
            self.present |= bit
            if healthy:
                self.health |= bit


def _axis(value: int) -> float:
    return max(-1.0, min(1.0, value / 1000.0))


def _e7(degrees: float) -> int:
    return round(degrees * 1e7)


def _fixed(text: bytes, size: int) -> list[int]:
    return list(text[:size].ljust(size, b"\0"))


def _text(value: Any) -> str:
    if isinstance(value, bytes):
        value = value.decode("ascii", "replace")
    return str(value).split("\0", 1)[0]
