"""The MAVLink vehicle's telemetry: pure encoders from :class:`VehicleState` to pymavlink
messages, and :class:`TelemetrySender`, which sends them to every link at their rates.
"""

from __future__ import annotations

import math
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas.autonomy.geo import to_e7
from platformd.mavlink import modes
from platformd.mavlink.link import LinkCore
from platformd.mavlink.model import CameraInfo, VehicleState
from platformd.mavlink.modes import FlightMode


class TelemetrySender(LinkCore):
    """Heartbeats, position, status and home to every link, each at its own rate."""

    def _init_telemetry(self, rates: tuple[float, float, float]) -> None:
        self.heartbeat_hz, self.position_hz, self.status_hz = rates
        self._due: dict[str, float] = {}

    def _send_due_telemetry(self, now: float) -> None:
        if self._due_now("heartbeat", self.heartbeat_hz, now):
            self._broadcast(heartbeat(self.state))
            if self.camera is not None:
                self._broadcast(camera_heartbeat(), modes.CAMERA_COMPONENT)
        if self._due_now("position", self.position_hz, now):
            for message in position_messages(self.state, self._boot_ms(now)):
                self._broadcast(message)
        if self._due_now("status", self.status_hz, now):
            for message in status_messages(self.state):
                self._broadcast(message)
        if self._due_now("home", self.status_hz / 5, now):
            home = home_position(self.state)
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


def heartbeat(state: VehicleState) -> Any:
    """The vehicle's HEARTBEAT: its mode, armed flag and state."""
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


def camera_heartbeat() -> Any:
    return mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_CAMERA,
        mavlink.MAV_AUTOPILOT_INVALID,
        0,
        0,
        mavlink.MAV_STATE_ACTIVE,
        3,
    )


def position_messages(state: VehicleState, boot_ms: int) -> list[Any]:
    """GPS_RAW_INT, GLOBAL_POSITION_INT, VFR_HUD and ATTITUDE, as far as known."""
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
                to_e7(fix.latitude),
                to_e7(fix.longitude),
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
    heading = heading_deg(state)
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
                to_e7(lat),
                to_e7(lon),
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


def heading_deg(state: VehicleState) -> float | None:
    """Degrees from north: the pose's, else the IMU's; None if neither knows."""
    pose = state.pose
    if pose is not None and pose.heading_known:
        return pose.heading_deg
    attitude = state.attitude
    if attitude is not None:
        return (90.0 - attitude.yaw_deg) % 360.0  # the IMU's yaw is ENU's, from east
    return None


def status_messages(state: VehicleState) -> list[Any]:
    """SYS_STATUS, BATTERY_STATUS (with a battery) and MISSION_CURRENT."""
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
        heading = heading_deg(state) is not None
        sensors.add(mavlink.MAV_SYS_STATUS_SENSOR_3D_MAG, True, state.imu_ok and heading)
    if state.inside_fence is not None:
        sensors.add(mavlink.MAV_SYS_STATUS_GEOFENCE, True, state.inside_fence)
    if state.prearm_ok is not None:  # "always healthy when armed" (MAVLink's definition)
        sensors.add(mavlink.MAV_SYS_STATUS_PREARM_CHECK, True, state.prearm_ok or state.armed)
    controller = state.controller
    # Fitted and not heard from yet (the driver still bringing it up): present, not healthy.
    sensors.add(
        mavlink.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS,
        state.motor_present or controller is not None,
        controller is not None and controller.connected,
    )
    if controller is not None:
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
    out.append(mission_current(state))
    return out


def mission_current(state: VehicleState) -> Any:
    """The patrol's target as a mission item (route index + 1: item 0 is home)."""
    seqs = state.waypoint_seqs
    if state.waypoint is None:
        seq = 0
    elif state.waypoint < len(seqs):
        seq = seqs[state.waypoint]
    else:
        seq = state.waypoint + 1
    total = seqs[-1] + 1 if seqs else state.waypoints + 1
    return mavlink.MAVLink_mission_current_message(seq, total)


def home_position(state: VehicleState) -> Any | None:
    """HOME_POSITION, None before a home is known."""
    home = state.home
    if home is None:
        return None
    lat, lon, alt = home
    return mavlink.MAVLink_home_position_message(
        to_e7(lat), to_e7(lon), round(alt * 1000), 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0, 0, 0
    )


def autopilot_version(system_id: int) -> Any:
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
        system_id,
    )


def camera_information(camera: CameraInfo) -> Any:
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


def video_stream_information(camera: CameraInfo) -> Any:
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


def _fixed(text: bytes, size: int) -> list[int]:
    return list(text[:size].ljust(size, b"\0"))
