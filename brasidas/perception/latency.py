"""How late the lidar's speed limits reach the motors, measured, so the stop allows for it.

A limit computed from a scan stays in force until the next scan's limit replaces it: the robot
drives on it from the moment that scan was taken until the next limit is published. On a quiet
machine that is a revolution and the analysis (~0.11 s at 10 Hz), which ``lidar.reaction_s``
already allows for. On a starved CPU the loop stalls for hundreds of milliseconds (every
process on the machine waits its turn), the next limit comes that much later, and the robot
covers speed x stall more than the stopping distance assumed: at the end of an approach it
went 0.35 m past its clearance. So each published limit measures the time since the previous
scan ended; the largest of the last ``WINDOW_S`` beyond the nominal is added to the dead time
the next limits are computed with (a slower approach while the machine is busy, the usual one
once it has been quiet for the window). Pure: times come in as parameters.
"""

from __future__ import annotations

import collections
import math

WINDOW_S = 10.0
"""How long a measured stall keeps counting: stalls come in bursts while the machine is busy."""
ANALYSIS_S = 0.05
"""The analysis and delivery a quiet machine needs, on top of a revolution."""
MAX_EXTRA_S = 1.0
"""The most added: by then the robot only crawls near anything (1 m/s within 2.5 m)."""


class UpdateLatency:
    """The extra dead time (seconds) the stopping distance must allow for, from the measured
    gaps between a scan's end and the next limit's publication."""

    def __init__(self, scan_period_s: float, cap_s: float) -> None:
        self.nominal_s = scan_period_s + ANALYSIS_S
        """What ``lidar.reaction_s`` already covers: a revolution and the analysis."""
        self.cap_s = cap_s
        """The most added (:data:`MAX_EXTRA_S`)."""
        self._samples: collections.deque[tuple[float, float]] = collections.deque()
        self._last_scan_end: float | None = None
        self.worst_s = 0.0
        """The largest gap measured (since start): the counters show it."""

    def extra(self, now: float) -> float:
        """The dead time to add for limits published at ``now``: the worst recent gap beyond
        the nominal, and at least how late this update already is."""
        while self._samples and now - self._samples[0][0] > WINDOW_S:
            self._samples.popleft()
        worst = max((gap for _at, gap in self._samples), default=0.0)
        if self._last_scan_end is not None:
            worst = max(worst, now - self._last_scan_end)
        return min(self.cap_s, max(0.0, worst - self.nominal_s))

    def published(self, now: float, scan_end: float) -> None:
        """Limits computed from the scan that ended at ``scan_end`` were published at ``now``."""
        if self._last_scan_end is not None:
            gap = now - self._last_scan_end
            self._samples.append((now, gap))
            self.worst_s = max(self.worst_s, gap)
        self._last_scan_end = scan_end

    def reset(self) -> None:
        """The lidar went blind (stopped): the next scan starts afresh."""
        self._last_scan_end = None


class DriveSpeed:
    """The speed the drive has reached (m/s, forward positive), modelled from the commands:
    an open-loop drive follows its command with a first-order lag, so while limits come down
    during an approach the robot goes faster than the last one (about twice as fast at the
    end of a stop at a 0.25 s lag and 0.5 s dead time): the limits judge that speed."""

    def __init__(self, lag_s: float) -> None:
        self.lag_s = lag_s
        self._at: float | None = None
        self._speed = 0.0
        self._command = 0.0

    def commanded(self, now: float, speed_mps: float) -> None:
        """The motors were commanded ``speed_mps`` at ``now``."""
        self._speed = self.at(now)
        self._at = now
        self._command = speed_mps

    def at(self, now: float) -> float:
        """The modelled speed at ``now``."""
        if self._at is None:
            return 0.0
        blend = 1.0 - math.exp(-max(0.0, now - self._at) / self.lag_s)
        return self._speed + (self._command - self._speed) * blend
