"""RC_CHANNELS_OVERRIDE read as the joystick: ArduRover's channel map (steering on channel 1,
throttle on channel 3, PWM 1000 to 2000 µs about 1500).

MAVProxy's ``rc 3 1600`` and QGroundControl's virtual joystick in RC mode send it. It goes the
way MANUAL_CONTROL goes (the override holder only, the deadman, the speed cap, the failsafe
ladder): this module only turns pulse widths into the velocity request's two axes.
"""

from __future__ import annotations

from typing import Any

STEERING_CHANNEL = 1
THROTTLE_CHANNEL = 3
CENTRE_US = 1500
SPAN_US = 500
"""Full deflection: 1000 or 2000 µs."""
DEAD_BAND_US = 30
"""Around the centre: a stick at rest (or a trim off by a few µs) is zero, not a creep."""
RELEASED = (0, 65535)
"""0: the channel goes back to the radio; UINT16_MAX: ignore it (MAVLink 2). Either way no
ground-station command on it: zero."""


def rc_velocity(message: Any) -> tuple[float, float]:
    """(linear forward, angular to the left), each in [-1, 1]; ArduRover's steering is
    positive to the right."""
    throttle = _stick(getattr(message, f"chan{THROTTLE_CHANNEL}_raw"))
    steering = _stick(getattr(message, f"chan{STEERING_CHANNEL}_raw"))
    return throttle, -steering


def _stick(pulse_us: int) -> float:
    if pulse_us in RELEASED:
        return 0.0
    offset = pulse_us - CENTRE_US
    if abs(offset) <= DEAD_BAND_US:
        return 0.0
    return max(-1.0, min(1.0, offset / SPAN_US))
