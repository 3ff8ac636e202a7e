"""The station's telemetry receiver and annunciator (the seed's Status Display, ch. 11 §4.2).

:mod:`.stats` (loss and silence) and :mod:`brasidas.annunciator` (warnings) are pure;
:mod:`.link` verifies and merges one platform's datagrams; :mod:`.receiver` is the actor that
binds the sockets and asks each connected platform for its stream.
"""

from __future__ import annotations

from brasidas.annunciator import (
    CONNECTIONS_REFUSED,
    CONTROL_TAKEN,
    CONTROLLER_OVER_TEMPERATURE,
    GPS_FIX_LOST,
    LINK_DEGRADED,
    LINK_LOST,
    LOW_BATTERY,
    NOTIFICATION_GROUP,
    PATROL_HOLDING,
    SENSOR_STALE,
    STREAM_FAILED,
    Alert,
    Annunciator,
    Change,
)
from stationd.context import StationContext
from stationd.telemetry.link import TelemetryLink
from stationd.telemetry.receiver import TelemetryReceiver, receive_host
from stationd.telemetry.stats import LinkStats

__all__ = [
    "CONNECTIONS_REFUSED",
    "CONTROLLER_OVER_TEMPERATURE",
    "CONTROL_TAKEN",
    "GPS_FIX_LOST",
    "LINK_DEGRADED",
    "LINK_LOST",
    "LOW_BATTERY",
    "NOTIFICATION_GROUP",
    "PATROL_HOLDING",
    "SENSOR_STALE",
    "STREAM_FAILED",
    "Alert",
    "Annunciator",
    "Change",
    "LinkStats",
    "TelemetryLink",
    "TelemetryReceiver",
    "async_setup",
    "receive_host",
]


async def async_setup(ctx: StationContext) -> None:
    receiver = TelemetryReceiver(ctx)
    ctx.api.add("get_telemetry", receiver.api_get_telemetry, session_required=False)
    ctx.api.add(
        "telemetry_notifications", receiver.api_telemetry_notifications, session_required=False
    )
    ctx.supervisor.start(receiver)
