"""Every bus topic, declared once. Retained topics hand their last value to new subscribers."""

from __future__ import annotations

from typing import Any

from brasidas.bus import Topic
from brasidas.messages import (
    LightsState,
    OverrideState,
    Position,
    SessionClosed,
    SessionOpened,
    SystemCommand,
    Velocity,
)

# Signaling
SYSTEM_COMMANDS: Topic[SystemCommand] = Topic("system_commands")
SESSION_OPENED: Topic[SessionOpened] = Topic("session_opened")
SESSION_CLOSED: Topic[SessionClosed] = Topic("session_closed")

# Mode and motion
OVERRIDE_STATE: Topic[OverrideState] = Topic("override_state", retain=True)
CMD_VEL: Topic[Velocity] = Topic("cmd_vel")
"""Autonomy's velocity commands; obeyed only in Autonomous Mode."""

# Platform state reported by beacons and telemetry
LIGHTS_STATE: Topic[LightsState] = Topic("lights_state", retain=True)
POSITION: Topic[Position] = Topic("position", retain=True)

# --------------------------------------------------------------------------- station
# Published by the station's connection manager with the stationd.client.PlatformConnection.
PLATFORM_CONNECTED: Topic[Any] = Topic("platform_connected")
PLATFORM_DISCONNECTED: Topic[Any] = Topic("platform_disconnected")
