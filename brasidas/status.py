"""The 32-bit platform status word carried by beacons (and telemetry). The bit layout lives here only.

bit 0      manual override (MOVRD) engaged (teleop mode)
bit 1      main lights on
bit 2      positional lights on
bits 3-4   coarse battery: 0 unknown, 1 low, 2 medium, 3 high
bit 5      GPS fix
bit 6      streaming (at least one media stream sending)
bit 7      a station session is open
bit 8      motor controller connected
bit 9      fault (an actor reports a failure: controller lost, stream failed, IMU missing)
bit 10     autonomy active: the patrol is running (patrolling, or holding for safety)
bits 11-31 reserved, zero
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import IntEnum


class Battery(IntEnum):
    UNKNOWN = 0
    LOW = 1
    MEDIUM = 2
    HIGH = 3


MOVRD = 1 << 0
MAIN_LIGHTS = 1 << 1
POSITIONAL_LIGHTS = 1 << 2
BATTERY_SHIFT = 3
BATTERY_MASK = 0b11 << BATTERY_SHIFT
GPS_FIX = 1 << 5
STREAMING = 1 << 6
SESSION = 1 << 7
CONTROLLER = 1 << 8
FAULT = 1 << 9
AUTONOMY = 1 << 10


@dataclass(frozen=True)
class StatusWord:
    movrd: bool = False
    main_lights: bool = False
    positional_lights: bool = False
    battery: Battery = Battery.UNKNOWN
    gps_fix: bool = False
    streaming: bool = False
    session: bool = False
    controller: bool = False
    fault: bool = False
    autonomy: bool = False

    def encode(self) -> int:
        word = int(self.battery) << BATTERY_SHIFT
        for flag, bit in self._flags():
            if flag:
                word |= bit
        return word

    def _flags(self) -> tuple[tuple[bool, int], ...]:
        return (
            (self.movrd, MOVRD),
            (self.main_lights, MAIN_LIGHTS),
            (self.positional_lights, POSITIONAL_LIGHTS),
            (self.gps_fix, GPS_FIX),
            (self.streaming, STREAMING),
            (self.session, SESSION),
            (self.controller, CONTROLLER),
            (self.fault, FAULT),
            (self.autonomy, AUTONOMY),
        )

    @classmethod
    def decode(cls, word: int) -> StatusWord:
        return cls(
            movrd=bool(word & MOVRD),
            main_lights=bool(word & MAIN_LIGHTS),
            positional_lights=bool(word & POSITIONAL_LIGHTS),
            battery=Battery((word & BATTERY_MASK) >> BATTERY_SHIFT),
            gps_fix=bool(word & GPS_FIX),
            streaming=bool(word & STREAMING),
            session=bool(word & SESSION),
            controller=bool(word & CONTROLLER),
            fault=bool(word & FAULT),
            autonomy=bool(word & AUTONOMY),
        )
