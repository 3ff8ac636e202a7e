"""Every bus topic, declared once. Retained topics hand their last value to new subscribers."""

from __future__ import annotations

from typing import TYPE_CHECKING

from brasidas.bus import Topic
from brasidas.messages import (
    ArmingState,
    Attitude,
    Automations,
    CommandAge,
    CommandReceived,
    CommandSent,
    ControllerStatus,
    ControlState,
    FailsafeState,
    GpsFix,
    GpsFixLost,
    GpsStats,
    ImuStatus,
    LightsState,
    MotionState,
    OverrideState,
    PatrolStatus,
    PlatformHealth,
    PlatformLink,
    PlatformSighting,
    PoseEstimate,
    Position,
    SafetyNotice,
    SessionClosed,
    SessionOpened,
    SpeedCap,
    StationNotification,
    StreamStatus,
    TelemetrySnapshot,
    Velocity,
    VelocityLinkStats,
)
from brasidas.perception.messages import (
    FusedPosition,
    LidarPose,
    PoseHold,
    Proximity,
    RobotScan,
)

if TYPE_CHECKING:  # numpy: not for every importer of the topics
    from brasidas.perception.view import GridImage

# Signaling
SESSION_OPENED: Topic[SessionOpened] = Topic("session_opened")
SESSION_CLOSED: Topic[SessionClosed] = Topic("session_closed")

# Mode and motion
OVERRIDE_STATE: Topic[OverrideState] = Topic("override_state", retain=True)
CONTROL_STATE: Topic[ControlState] = Topic("control_state", retain=True)
"""Who holds control (platformd.authority): published on claim, takeover and release."""
FAILSAFE_STATE: Topic[FailsafeState] = Topic("failsafe_state", retain=True)
"""The failsafe ladder's step (platformd.failsafe): hold and release while teleoperated."""
SPEED_CAP: Topic[SpeedCap] = Topic("speed_cap", retain=True)
"""The teleop speed limit for the measured latency (platformd.speedcap)."""
ARMING_STATE: Topic[ArmingState] = Topic("arming_state", retain=True)
"""Armed or disarmed (platformd.arming): the motion arbiter holds zero while disarmed."""
SAFETY_NOTICES: Topic[SafetyNotice] = Topic("safety_notices")
"""Pre-arm refusals, the autostart countdown, stops (platformd.arming): STATUSTEXT, logs."""
CMD_VEL: Topic[Velocity] = Topic("cmd_vel")
"""Autonomy's velocity commands; obeyed only in Autonomous Mode."""
MOTOR_COMMAND: Topic[Velocity] = Topic("motor_command")
"""What the motors must do now: published only by the motion arbiter, obeyed by the driver."""

# Platform state reported by beacons and telemetry
LIGHTS_STATE: Topic[LightsState] = Topic("lights_state", retain=True)
POSITION: Topic[Position] = Topic("position", retain=True)

# --------------------------------------------------------------------------- station
PLATFORM_CONNECTED: Topic[PlatformLink] = Topic("platform_connected")
"""A session with a platform opened (stationd.connections); the connection is in ctx.connections."""
PLATFORM_DISCONNECTED: Topic[PlatformLink] = Topic("platform_disconnected")
"""That session ended (closed, lost or refused), with the reason."""
PLATFORM_DISCOVERED: Topic[PlatformSighting] = Topic("platform_discovered")
"""A platform's first beacon (stationd.discovery)."""
PLATFORM_LOST: Topic[PlatformSighting] = Topic("platform_lost")
"""No beacon from a platform for ``discovery.expiry`` seconds."""
COMMAND_SENT: Topic[CommandSent] = Topic("command_sent")
"""A system command this station sent for its operator, and the answer (stationd.connections)."""

# --------------------------------------------------------------------------- velocity stream (issue 3)
TELEOP_VELOCITY: Topic[Velocity] = Topic("teleop_velocity")
"""Valid $PVEL velocities from the session holding the manual override (platformd.velocity)."""
VELOCITY_LINK_STATS: Topic[VelocityLinkStats] = Topic("velocity_link_stats", retain=True)
"""The velocity receiver's accepted/dropped counters, published when they change (≤ 1 Hz)."""
COMMAND_AGE: Topic[CommandAge | None] = Topic("command_age", retain=True)
"""The holder's velocity packets' measured age (platformd.velocity): the speed cap's command
latency. None when no packet with a send time arrived in the last second."""
MOTION_STATE: Topic[MotionState] = Topic("motion_state", retain=True)
"""The motion arbiter's mode, deadman and last motor command (platformd.arbiter)."""
CONTROLLER_STATUS: Topic[ControllerStatus] = Topic("controller_status", retain=True)
"""The motor controller: connected, battery, heatsinks, currents (platformd.motor)."""

# --------------------------------------------------------------------------- telemetry (issue 4)
PLATFORM_HEALTH: Topic[PlatformHealth] = Topic("platform_health", retain=True)
"""Coarse battery, GPS fix, streaming, controller and fault flags (platformd.telemetry; beacon)."""
STATION_NOTIFICATIONS: Topic[StationNotification] = Topic("station_notifications")
"""Station only: group 90 notifications, e.g. annunciator warnings raised and cleared."""
TELEMETRY_SNAPSHOTS: Topic[TelemetrySnapshot] = Topic("telemetry_snapshots")
"""Station side: each platform's snapshot after every accepted telemetry datagram."""

# --------------------------------------------------------------------------- media (issue 5)
STREAM_STATES: Topic[StreamStatus] = Topic("stream_states")
"""A media stream's state changed (idle, playing, paused, failed with its reason)."""

# --------------------------------------------------------------------------- sensors (issue 4)
GPS_FIX: Topic[GpsFix] = Topic("gps_fix", retain=True)
"""One fix per receiver epoch (platformd.gps)."""
GPS_FIX_LOST: Topic[GpsFixLost] = Topic("gps_fix_lost")
"""The fix went away (receiver says none, silent, or port gone); GPS_FIX resumes it."""
GPS_STATS: Topic[GpsStats] = Topic("gps_stats", retain=True)
"""Sentence counters by type and drops by reason, at most once a second."""
ATTITUDE: Topic[Attitude] = Topic("attitude", retain=True)
"""IMU orientation (Madgwick), at most about 10 Hz (platformd.imu)."""
IMU_STATUS: Topic[ImuStatus] = Topic("imu_status", retain=True)
"""IMU health, temperature and counters, about once a second."""

# --------------------------------------------------------------------------- autonomy (issue 12)
POSE: Topic[PoseEstimate] = Topic("pose", retain=True)
"""Where the robot is (platformd.autonomy.localization today; a SLAM actor would publish here)."""
PATROL_STATUS: Topic[PatrolStatus] = Topic("patrol_status", retain=True)
"""The patrol's state, target, lap and planned path, on every change (platformd.autonomy)."""
AUTOMATIONS: Topic[Automations] = Topic("automations", retain=True)
"""Onboard automations switched on or off (R-3): see :func:`platformd.automation.report_switch`."""

# --------------------------------------------------------------------------- recorder (issue 23)
COMMAND_RECEIVED: Topic[CommandReceived] = Topic("command_received")
"""Every system command and control method a station sent, with the sender and the answer."""

# --------------------------------------------------------------------------- perception (issue 30)
LIDAR_SCAN: Topic[RobotScan] = Topic("lidar_scan", retain=True)
"""Each lidar revolution in the robot's frame, with its obstacles (platformd.lidar)."""
PROXIMITY: Topic[Proximity] = Topic("proximity", retain=True)
"""Speed limits for what the lidar sees (platformd.lidar); the motion arbiter applies them."""
FUSED_POSE: Topic[FusedPosition] = Topic("fused_pose", retain=True)
"""The lidar localization's fused pose, at most 5 a second (platformd.perception_view)."""
OCCUPANCY_GRID: Topic[GridImage] = Topic("occupancy_grid", retain=True)
"""The occupancy grid as a small image, every few seconds while it changes (likewise)."""
LIDAR_POSE: Topic[LidarPose] = Topic("lidar_pose", retain=True)
"""The lidar localization's fused pose, after each scan (platformd.lidar_localization): what
``POSE`` rests on while it registers (platformd.autonomy.localization)."""
POSE_HOLD: Topic[PoseHold] = Topic("pose_hold", retain=True)
"""Why ``LIDAR_POSE`` must not be driven on now, or "" (platformd.lidar_localization): autonomy
publishes no ``POSE`` from it and the patrol holds with the reason."""
GPS_ACCEPTED: Topic[GpsFix] = Topic("gps_accepted")
"""Each fix the lidar localization's gate did not refuse (all of them before it starts): the
only fixes the GPS+IMU filter follows while ``lidar.odometry`` is on."""
