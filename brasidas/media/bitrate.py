"""A NavCam bitrate that follows the link, from the receivers' RTCP reports (sans-IO).

Loss-based, as the loss half of Google's congestion control: every :data:`STEP_S` the worst
receiver's smoothed fraction of packets lost (RTCP receiver reports, counted before repair:
the link's own loss) decides. Above :data:`CONGESTED_LOSS` the link is over its capacity (a
full queue drops the excess) and the bitrate falls to what got through, less 5 %; below
:data:`CLEAN_LOSS` it climbs back by :data:`CLIMB` a step toward the configured ceiling; in
between (a mesh's routine random loss, which retransmission repairs) it holds. Never below
``floor_kbps``, never above the ceiling the framerate allows.
"""

from __future__ import annotations

STEP_S = 0.5
CONGESTED_LOSS = 0.10
CLEAN_LOSS = 0.02
CLIMB = 1.08
SMOOTHING = 0.5
"""Weight of the newest report in the smoothed loss."""
COLLAPSE_LOSS = 0.35
"""A report losing more than this is a capacity drop, not a mesh's random loss (a single
report at 10 % random loss exceeded 20 % now and then, measured): the bitrate
falls on that report, to what got through, without waiting for the smoothing (measured at
2 Mbit/s → 500 kbit/s: smoothed alone, three steps and 1.5 s of a full queue dropping)."""
COLLAPSE_CONFIRM_S = 1.0
DECREASE_GAP_S = 0.25
"""Decreases no closer than this (a report or two apart)."""


class BitrateController:
    """The target bitrate (kbit/s) for the encoder."""

    def __init__(self, ceiling_kbps: int, floor_kbps: int) -> None:
        self.floor_kbps = floor_kbps
        self.target_kbps = float(ceiling_kbps)
        self.loss = 0.0
        """Smoothed fraction lost of the worst receiver."""
        self.decreases = 0
        self.collapsed_at: float | None = None
        """When a capacity drop was last confirmed: a report losing over
        :data:`COLLAPSE_LOSS`, then within :data:`COLLAPSE_CONFIRM_S` another losing over
        :data:`CONGESTED_LOSS` (the queue still overflowing; under a loaded emulator a single
        report spiked now and then)."""
        self._collapse_report_at: float | None = None
        self._last_step: float | None = None

    def update(self, loss: float | None, ceiling_kbps: int, now: float) -> int | None:
        """A report's fraction lost (None: no receiver reported) at ``now``; the new
        target when it changed, else None."""
        if loss is not None:
            self.loss = SMOOTHING * loss + (1 - SMOOTHING) * self.loss
        collapse = loss is not None and loss > COLLAPSE_LOSS
        last = self._collapse_report_at
        if loss is not None and loss > CONGESTED_LOSS and last is not None:
            if 0 < now - last <= COLLAPSE_CONFIRM_S:
                self.collapsed_at = now
        if collapse:
            self._collapse_report_at = now
        gap = DECREASE_GAP_S if collapse else STEP_S
        if self._last_step is not None and now - self._last_step < gap:
            return None
        self._last_step = now
        before = self.effective_kbps(ceiling_kbps)
        if loss is not None and (collapse or self.loss > CONGESTED_LOSS):
            # What got through: over capacity, the loss is the excess (a full queue drops it).
            worst = max(loss, self.loss) if collapse else self.loss
            lowered = min(self.target_kbps, float(ceiling_kbps)) * (1 - worst) * 0.95
            self.target_kbps = max(float(self.floor_kbps), lowered)
            self.decreases += 1
        elif loss is not None and self.loss < CLEAN_LOSS:
            # Up to the ceiling; a target above it (a lower framerate's) is kept for later.
            raised = max(self.target_kbps * CLIMB, self.target_kbps + 10)
            self.target_kbps = max(self.target_kbps, min(raised, float(ceiling_kbps)))
        after = self.effective_kbps(ceiling_kbps)
        return after if after != before else None

    def effective_kbps(self, ceiling_kbps: int) -> int:
        """What the encoder is set to: the target within the framerate's ceiling."""
        return max(self.floor_kbps, round(min(self.target_kbps, float(ceiling_kbps))))


THIN_AFTER_COLLAPSE_S = 10.0
"""Frames are thinned only this long after a capacity drop was seen: a bitrate lowered by a
mesh's random loss (which loss alone cannot tell apart) keeps every frame."""
MIN_THINNED_FPS = 10
"""Thinning never sends fewer frames than this (nor thins a stream already at or below it)."""


def frame_thinning(framerate: int, bitrate_kbps: int, ceiling_kbps: int) -> int:
    """Send one frame in N when the link forced the bitrate far below the framerate's share:
    fewer frames with twice the bits each stay legible, where every frame at a third of its
    bits smears and its larger losses freeze the picture. 1: every frame."""
    if ceiling_kbps <= 0 or framerate <= MIN_THINNED_FPS:
        return 1
    share = bitrate_kbps / ceiling_kbps
    wanted = 1 if share >= 0.5 else 2 if share >= 0.25 else 3
    return max(1, min(wanted, framerate // MIN_THINNED_FPS))
