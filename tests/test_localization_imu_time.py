"""The localization turns the heading by the IMU's readings at their own times (their stamps,
the IMU's sample clock), not at the moment a loaded event loop hands them over."""

from __future__ import annotations

import math
import time

from brasidas.autonomy.localization import FilterParameters
from brasidas.bus import Bus
from brasidas.messages import Attitude
from platformd.autonomy.localization import Localization

RATE = math.radians(60.0)
"""The start's turn on the spot (rad/s)."""


def test_readings_handed_over_together_turn_the_heading_at_their_own_rate() -> None:
    """Six readings 0.1 s apart of a 60°/s turn, handed over at once (a stalled loop runs the
    IMU's queued batches back to back): the heading turns at 60°/s. Timed by their arrival,
    the yaw's change over microseconds read as thousands of °/s, and it was dead-reckoned on
    at that rate until the next reading: the heading tens of degrees off in every turn."""
    localization = Localization(Bus(), FilterParameters(1.67, 1.5), rate_hz=10.0)
    localization._clock = time.monotonic  # as run() sets it: the loop's clock
    localization.start()
    start = time.monotonic() - 0.6
    localization.filter.command(start, 0.0, 1.0)  # the turn asked for, as it starts
    for k in range(6):
        at = start + 0.1 * k
        localization._on_attitude(
            Attitude(1, 0, 0, 0, 0, 0, math.degrees(RATE * (at - start)), stamp=at)
        )
    later = time.monotonic() + 0.1
    yaw = localization.filter.estimate(later).yaw
    truth = math.remainder(RATE * (later - start), math.tau)
    assert abs(math.degrees(math.remainder(yaw - truth, math.tau))) < 2.0, (yaw, truth)
