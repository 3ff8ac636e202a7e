"""When the NavCam's encoder must make a keyframe (sans-IO: the caller passes ``now``).

The encoders' own GOP settings cannot follow a live framerate change (x264enc's
``key-int-max`` and openh264enc's ``gop-size`` are fixed once the encoder runs, and the
hardware encoders differ again), so the sender owns the cadence instead: the encoder's own
interval is set long, and :class:`KeyframeClock` asks for a keyframe (a force-key-unit event,
which every encoder understands) every ``interval_s`` of frames at the *current* framerate,
and at once when a receiver reports a loss (RTCP PLI/FIR), no more often than
``min_request_gap_s`` after the last keyframe made *on request*, so a burst of requests from a
lossy link cannot turn every frame into a keyframe. A request that comes sooner is deferred
to the end of that gap, never dropped: it may come from a receiver that lost the keyframe just
made (the one a cut swallowed), and dropped, it left that receiver frozen to the next periodic
keyframe, a second later. A periodic keyframe does not hold a request back: after a blackout
the one made during it was lost with it, and waiting out its gap kept the picture frozen up to
250 ms longer (measured: after 3 of 6 blackouts the request was deferred, and the picture
came back 107-152 ms after the link; about 30 ms after the others). At most one periodic
keyframe a second more.
"""

from __future__ import annotations

from dataclasses import dataclass

KEYFRAME_INTERVAL_S = 1.0
"""Periodic keyframes: a new viewer starts within a second, a lost repair heals within one."""
REFRESH_KEYFRAME_INTERVAL_S = 5.0
"""The clock's interval under intra refresh: x264 then answers a forced key unit with a new
refresh sweep (not an IDR), which it makes every second anyway; kept for encoders that would
make an IDR of it."""
MIN_REQUEST_GAP_S = 0.25
"""Keyframes on request no closer than this (a keyframe is 5-10 times a delta frame)."""


@dataclass
class KeyframeCounters:
    periodic: int = 0
    requested: int = 0
    """Requests (PLI/FIR, a new viewer) answered by a keyframe."""
    deferred: int = 0
    """Requests answered only at the end of the rate limit's gap (a keyframe had just been
    made)."""
    resumed: int = 0
    """Keyframes after the sender paused for a link's queue to drain."""


class KeyframeClock:
    """Decides, frame by frame, whether the encoder must make the next frame a keyframe."""

    def __init__(
        self,
        framerate: int,
        *,
        interval_s: float = KEYFRAME_INTERVAL_S,
        min_request_gap_s: float = MIN_REQUEST_GAP_S,
    ) -> None:
        self.interval_s = interval_s
        self.min_request_gap_s = min_request_gap_s
        self.interval_frames = 1
        self.set_framerate(framerate)
        self.counters = KeyframeCounters()
        self._since_keyframe = 0
        self._pending = False
        self._last_forced: float | None = None
        self._last_requested: float | None = None
        """When the last keyframe made on request was (the rate limit counts from it)."""
        self.congested = False
        """The link's queue overflowed lately (the sender's bitrate collapsed): a periodic
        keyframe is then likely queued, not lost, and a request soon after it stale, so the
        limit counts from every keyframe (two within 250 ms would refill the queue)."""

    def restart(self) -> None:
        """A new encoder: its first frame is a keyframe; the counters go on."""
        self._since_keyframe = 0
        self._pending = False
        self._last_forced = None
        self._last_requested = None

    def set_framerate(self, framerate: int) -> None:
        """The interval in frames follows the framerate (5 fps: every 5th frame)."""
        self.interval_frames = max(1, round(framerate * self.interval_s))

    def request(self, now: float) -> None:
        """A receiver asks for a keyframe: the next frame is one, or the first frame
        ``min_request_gap_s`` after the last keyframe made on request."""
        if self._pending:
            return
        self._pending = True
        self.counters.requested += 1
        if not self._gap_over(now):
            self.counters.deferred += 1

    def _gap_over(self, now: float) -> bool:
        last = self._last_forced if self.congested else self._last_requested
        return last is None or now - last >= self.min_request_gap_s

    def answers_now(self, now: float) -> bool:
        """Whether a request waits and its gap is over: the next frame answers it, so a
        copy of the newest frame may be encoded at once (:mod:`~brasidas.media.keyframe_now`)
        instead of waiting for the camera's next."""
        return self._pending and self._gap_over(now)

    def on_frame(self, now: float, resume: bool = False) -> bool:
        """A raw frame goes into the encoder: True when it must be encoded as a keyframe.
        ``resume``: the first frame after the sender paused for a link's queue to drain (a
        keyframe whatever the gap: those before it were lost to the queue)."""
        self._since_keyframe += 1
        periodic = self._since_keyframe >= self.interval_frames
        asked = self._pending and self._gap_over(now)
        if resume:
            self.counters.resumed += 1
        elif not (periodic or asked or self._last_forced is None):
            return False
        if periodic and not asked and not resume and self._last_forced is not None:
            self.counters.periodic += 1
        if asked:
            self._last_requested = now
        self._pending = False
        self._since_keyframe = 0
        self._last_forced = now
        return True
