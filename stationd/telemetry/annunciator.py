"""The annunciator, shared with the platform's MAVLink endpoint: :mod:`brasidas.annunciator`
(the platform never imports the station)."""

from __future__ import annotations

from brasidas.annunciator import (
    CONTROL_TAKEN,
    CONTROLLER_OVER_TEMPERATURE,
    FAILED_STREAM_STATES,
    GPS_FIX_LOST,
    LINK_DEGRADED,
    LINK_LOST,
    LOW_BATTERY,
    MAP_REFUSED,
    NOTIFICATION_GROUP,
    PATROL_HOLDING,
    SENSOR_STALE,
    STREAM_FAILED,
    Alert,
    Annunciator,
    Change,
)

__all__ = [
    "CONTROLLER_OVER_TEMPERATURE",
    "CONTROL_TAKEN",
    "FAILED_STREAM_STATES",
    "GPS_FIX_LOST",
    "LINK_DEGRADED",
    "LINK_LOST",
    "LOW_BATTERY",
    "MAP_REFUSED",
    "NOTIFICATION_GROUP",
    "PATROL_HOLDING",
    "SENSOR_STALE",
    "STREAM_FAILED",
    "Alert",
    "Annunciator",
    "Change",
]
