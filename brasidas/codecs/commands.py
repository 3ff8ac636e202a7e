"""System command codes (seed table 10.1) and their ``key=value`` payload strings."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class CommandCode:
    group: int
    command: int

    def __str__(self) -> str:
        return f"{self.group}.{self.command}"


MANUAL_OVERRIDE = CommandCode(10, 0)
START_STREAMS = CommandCode(10, 1)
STOP_STREAMS = CommandCode(10, 2)
PAUSE_STREAMS = CommandCode(10, 3)
SET_FRAMERATE = CommandCode(10, 5)
MAIN_LIGHTS = CommandCode(10, 6)
POSITIONAL_LIGHTS = CommandCode(10, 7)
PATROL = CommandCode(10, 8)
AUTO_FRAMERATE = CommandCode(10, 9)
STREAM_RETRIES = CommandCode(10, 10)
DIAGNOSTICS = CommandCode(20, 0)
BATTERY_MONITOR = CommandCode(20, 4)

DESCRIPTIONS: dict[CommandCode, str] = {
    MANUAL_OVERRIDE: "manual override (MOVRD)",
    START_STREAMS: "start all streams",
    STOP_STREAMS: "stop all streams",
    PAUSE_STREAMS: "pause all streams",
    SET_FRAMERATE: "set a video stream's framerate",
    MAIN_LIGHTS: "main lights",
    POSITIONAL_LIGHTS: "positional lights",
    PATROL: "patrol automation on or off",
    AUTO_FRAMERATE: "automatic NavCam framerate switch (5/30 fps) on or off",
    STREAM_RETRIES: "retrying failed streams on or off",
    DIAGNOSTICS: "diagnostics report",
    BATTERY_MONITOR: "battery monitor",
}

OBSERVER_CODES = frozenset({START_STREAMS, STOP_STREAMS})
"""What a station that does not hold control may send: start and stop its own copy of the
streams (each session its own destination). Everything else is a control command (issue 13)."""

STATION_ONLY_GROUPS = frozenset({90, 91})
"""Group 90 (station notifications) and 91 never go to a platform."""

PAYLOAD_GROUPS = range(100, 111)


def describe(code: CommandCode) -> str | None:
    """What the code does, or None when it is not a known code."""
    if code in DESCRIPTIONS:
        return DESCRIPTIONS[code]
    if code.group in PAYLOAD_GROUPS:
        return f"payload group {code.group} command {code.command}"
    return None


class PayloadError(ValueError):
    """A payload string that does not parse."""


def parse_payload(payload: str) -> dict[str, str]:
    """``"a=1, b=x"`` → ``{"a": "1", "b": "x"}``. A bare word is a key with value ``""``."""
    result: dict[str, str] = {}
    if not payload.strip():
        return result
    for item in payload.split(","):
        key, sep, value = item.partition("=")
        key = key.strip()
        if not key:
            raise PayloadError(f"empty key in payload {payload!r}")
        result[key] = value.strip() if sep else ""
    return result


def format_payload(values: dict[str, Any]) -> str:
    return ",".join(f"{key}={value}" for key, value in values.items())


_TRUE = {"true", "on", "1", "yes"}
_FALSE = {"false", "off", "0", "no"}


def parse_switch(payload: str) -> bool:
    """The seed's "True"/"False"/"ON"/"OFF" payloads (also ``state=on``)."""
    text = payload.strip()
    if "=" in text:
        values = parse_payload(text)
        text = values.get("state", values.get("engaged", next(iter(values.values()), "")))
    word = text.strip().lower()
    if word in _TRUE:
        return True
    if word in _FALSE:
        return False
    raise PayloadError(f"expected ON/OFF or True/False, got {payload!r}")
