"""A local metric frame: east-north-up on the WGS-84 tangent plane at an origin."""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass


def to_e7(degrees: float) -> int:
    """Degrees in integer units of 1e-7 degree (about 1 cm), as MAVLink and beacons carry them."""
    return round(degrees * 1e7)


WGS84_A = 6_378_137.0
WGS84_F = 1.0 / 298.257223563
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)


@dataclass(frozen=True)
class LocalFrame:
    """ENU tangent plane at (``latitude``, ``longitude``): x east, y north, metres.

    Exact for the ellipsoid at the origin (ECEF through the tangent plane, heights taken as
    zero); over a few kilometres the plane departs from the ground by centimetres.
    """

    latitude: float
    longitude: float

    def to_local(self, latitude: float, longitude: float) -> tuple[float, float]:
        """(x east, y north) in metres of a WGS-84 position."""
        x0, y0, z0 = _ecef(self.latitude, self.longitude)
        x1, y1, z1 = _ecef(latitude, longitude)
        dx, dy, dz = x1 - x0, y1 - y0, z1 - z0
        sin_lat, cos_lat, sin_lon, cos_lon = self._trig()
        east = -sin_lon * dx + cos_lon * dy
        north = -sin_lat * cos_lon * dx - sin_lat * sin_lon * dy + cos_lat * dz
        return east, north

    def to_geo(self, x: float, y: float) -> tuple[float, float]:
        """(latitude, longitude) of a point of the plane (its foot on the ellipsoid)."""
        sin_lat, cos_lat, sin_lon, cos_lon = self._trig()
        x0, y0, z0 = _ecef(self.latitude, self.longitude)
        ex = x0 - sin_lon * x - sin_lat * cos_lon * y
        ey = y0 + cos_lon * x - sin_lat * sin_lon * y
        ez = z0 + cos_lat * y
        return _geodetic(ex, ey, ez)

    def _trig(self) -> tuple[float, float, float, float]:
        lat, lon = math.radians(self.latitude), math.radians(self.longitude)
        return math.sin(lat), math.cos(lat), math.sin(lon), math.cos(lon)


def centre_of(positions: Iterable[tuple[float, float]]) -> tuple[float, float]:
    """(latitude, longitude) of the middle of (longitude, latitude) positions, through
    Earth-centred coordinates: right across the 180° meridian and near the poles, where
    averaging degrees is not. Raises ValueError when they have no middle (spread round the
    globe)."""
    sx = sy = sz = 0.0
    count = 0
    for lon, lat in positions:
        la, lo = math.radians(lat), math.radians(lon)
        sx += math.cos(la) * math.cos(lo)
        sy += math.cos(la) * math.sin(lo)
        sz += math.sin(la)
        count += 1
    norm = math.sqrt(sx * sx + sy * sy + sz * sz)
    if count == 0 or norm < 1e-6 * count:
        raise ValueError("has no middle: it is spread round the globe")
    return math.degrees(math.asin(sz / norm)), math.degrees(math.atan2(sy, sx))


def heading_to_yaw(heading_deg: float) -> float:
    """Compass heading (clockwise from north, degrees) to ENU yaw (CCW from east, radians)."""
    return wrap(math.radians(90.0 - heading_deg))


def yaw_to_heading(yaw_rad: float) -> float:
    """ENU yaw to compass heading in [0, 360)."""
    return (90.0 - math.degrees(yaw_rad)) % 360.0


def wrap(angle: float) -> float:
    """An angle in radians wrapped to (-pi, pi]."""
    return math.atan2(math.sin(angle), math.cos(angle))


def _ecef(latitude: float, longitude: float) -> tuple[float, float, float]:
    lat, lon = math.radians(latitude), math.radians(longitude)
    n = WGS84_A / math.sqrt(1.0 - WGS84_E2 * math.sin(lat) ** 2)
    return (
        n * math.cos(lat) * math.cos(lon),
        n * math.cos(lat) * math.sin(lon),
        n * (1.0 - WGS84_E2) * math.sin(lat),
    )


def _geodetic(x: float, y: float, z: float) -> tuple[float, float]:
    lon = math.atan2(y, x)
    p = math.hypot(x, y)
    lat = math.atan2(z, p * (1.0 - WGS84_E2))
    for _ in range(5):  # converges to well under a millimetre in three
        n = WGS84_A / math.sqrt(1.0 - WGS84_E2 * math.sin(lat) ** 2)
        height = p / math.cos(lat) - n
        lat = math.atan2(z, p * (1.0 - WGS84_E2 * n / (n + height)))
    return math.degrees(lat), math.degrees(lon)
