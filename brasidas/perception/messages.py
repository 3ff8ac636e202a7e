"""Bus messages of perception (topics in :mod:`brasidas.topics`)."""

from __future__ import annotations

from dataclasses import dataclass

SEEN_KEEPOUT_PREFIX = "lidar:"
"""The ids of the keep-outs the platform makes of obstacles its lidar saw (temporary, never
stored in the map file)."""


@dataclass(frozen=True)
class Obstacle:
    """A cluster of returns, in the robot's frame at the scan (x forward, y left, metres)."""

    x_m: float
    y_m: float
    radius_m: float
    points: int


@dataclass(frozen=True)
class RobotScan:
    """One lidar revolution in the robot's frame, after the body, masks and noise are removed."""

    time: float
    """When its last frame arrived (the platform's monotonic clock)."""
    bearings_deg: tuple[float, ...]
    """Clockwise from the robot's forward axis, in [0, 360): every point of the revolution."""
    ranges_m: tuple[float, ...]
    """From the robot's centre; 0.0 = no return, or dropped (body, masked sector)."""
    points_used: int
    obstacles: tuple[Obstacle, ...]


@dataclass(frozen=True)
class Proximity:
    """How fast the robot may go for what the lidar sees (the motion arbiter applies it)."""

    time: float
    forward_limit: float
    """Largest forward speed, as a fraction of the platform's top speed (0: stop)."""
    reverse_limit: float
    """Largest reverse speed, likewise."""
    forward_free_m: float | None
    """Free distance ahead in the robot's corridor (None: nothing seen)."""
    reverse_free_m: float | None
    nearest_m: float | None
    """The nearest obstacle from the robot's centre, any direction."""
    nearest_bearing_deg: float | None
    """Its bearing, clockwise from the robot's forward axis."""
    reason: str
    """Why the limit is what it is ("" when the way is clear)."""
    turns: tuple[tuple[float, float, str], ...] = ()
    """Forward limits along arcs: (turn ratio, limit, reason) where the ratio is the command's
    angular over its linear (both fractions of full scale; positive: left), the corridor
    following the arc the robot drives (:func:`brasidas.perception.limits.forward_for`)."""
    sensor_nearest_m: float | None = None
    """The nearest return's distance from the sensor; kept while what was that close is
    held as gone into the sensor's blind zone."""


@dataclass(frozen=True)
class FusedPosition:
    """The lidar localization's fused pose on the globe (platformd.perception_view)."""

    time: float
    latitude: float
    longitude: float
    heading_deg: float
    """Clockwise from north."""
    x_m: float
    """In the localizer's local frame (east, north of its anchor), as recorded."""
    y_m: float
    yaw_rad: float
    """Counter-clockwise from east."""
    sigma_m: float
    source: str


@dataclass(frozen=True)
class LidarPose:
    """The lidar localization's fused pose (odometry, the map, gated GPS), in geo terms."""

    time: float
    """The scan (or fix) it is for (the platform's monotonic clock)."""
    latitude: float
    longitude: float
    yaw_rad: float
    """Counter-clockwise from east."""
    sigma_m: float
    sigma_yaw_rad: float
    source: str
    """"map+lidar", "gps+lidar", "lidar", "prior" or "none" (``FusedPose.source``)."""
    measured_at: float | None
    """When it last rested on a measurement (a registered scan, a map match or an accepted
    fix): dead reckoning since then is the commanded speed's and the gyro's."""


@dataclass(frozen=True)
class PoseHold:
    """Why the lidar localization's pose must not be driven on ("" when it may): searching a
    saved map for the robot, an ambiguous place, the match lost, or a map frame of the robot's
    own (no GPS ever: a route in latitude and longitude means nothing in it)."""

    reason: str
