"""A keyframe at once on request: the newest raw frame encoded again, not the next capture.

A receiver's request (PLI/FIR) reaches the encoder as a force-key-unit, which an encoder
applies to the next frame it is given: the camera's next capture, up to a frame interval
later (33 ms at 30 fps, 200 ms at 5 fps). Measured after a 300 ms blackout at 30 fps: the
request reached the sender 1 ms after the receiver's first packet and the keyframe left
22-38 ms after it, all of it the wait for the camera. :class:`KeyframeNow` keeps a reference
to the newest raw frame that went into the encoder and, when asked, gives the encoder a
copy of it from a thread of its own: the encoder's sink pad takes it under the same stream
lock as the camera's frames, so the two never interleave. The copy keeps the frame's capture
stamp (its glass-to-glass is the picture's true age) and is timestamped
:data:`INJECTED_PTS_STEP_NS` after it (the encoder and the RTP timestamps see time move on: a
new frame, not the old one again). A camera frame that reached the encoder first has
answered the request already, and the copy is then dropped: the caller's input probe decides
(:meth:`KeyframeNow.is_injecting`, :meth:`KeyframeNow.admit`).
"""

from __future__ import annotations

import threading
from typing import Any

from brasidas.media.gst import gst

INJECTED_PTS_STEP_NS = 1_000_000
"""The copy's timestamp after its original's: later (an encoder wants time to go forward),
and far below any camera's frame interval (the next capture stays later still)."""
_COPY_FLAGS_NAMES = ("FLAGS", "TIMESTAMPS", "META", "MEMORY")
"""A shallow copy: the pixels shared, the metadata (the capture stamp) copied."""


class KeyframeNow:
    """The newest raw frame, and a thread that gives the encoder a copy of it when asked.
    ``keep`` on the encoder's input (its streaming thread), ``ask`` from any thread, ``close``
    when the pipeline is torn down. One per pipeline."""

    def __init__(self, sink_pad: Any, name: str = "encoder") -> None:
        self._pad = sink_pad
        self._lock = threading.Lock()
        self._newest: Any = None
        """The newest raw frame into the encoder (a reference; read by the thread)."""
        self._last_pts = -1
        """The timestamp of the newest frame into the encoder, a camera's or a copy."""
        self._wake = threading.Event()
        self._closing = False
        self.injected = 0
        """Copies given to the encoder (each answered a request at once)."""
        self.dropped = 0
        """Copies dropped: a camera frame got to the encoder first."""
        self._thread = threading.Thread(target=self._run, name=f"keyframe-now:{name}", daemon=True)
        self._thread.start()

    def keep(self, buffer: Any) -> None:
        """Streaming thread, a camera frame into the encoder: the one to copy next."""
        if buffer is None:
            return
        with self._lock:
            self._newest = buffer
            self._last_pts = max(self._last_pts, int(buffer.pts))

    def ask(self) -> None:
        """Any thread: give the encoder a copy of the newest frame now."""
        self._wake.set()

    def is_injecting(self) -> bool:
        """In the encoder's input probe: whether this frame is a copy of ours (the probe runs
        on the thread that pushed it)."""
        # By its id: threading.current_thread() on a GStreamer thread would register a
        # dummy Thread for it, alive as long as GStreamer's pool keeps the thread.
        return threading.get_ident() == self._thread.ident

    def admit(self, buffer: Any, wanted: bool) -> bool:
        """In the encoder's input probe, for a copy: whether it goes in. Only if a request
        still waits for it (``wanted``: a camera frame may have answered it meanwhile) and it
        is newer than every frame the encoder has had."""
        with self._lock:
            if not wanted or buffer is None or int(buffer.pts) <= self._last_pts:
                self.dropped += 1
                return False
            self._last_pts = int(buffer.pts)
            self.injected += 1
            return True

    def close(self) -> None:
        """Stop the thread and let the frame go (the pipeline is already stopped: a copy
        being pushed returns at once)."""
        self._closing = True
        self._wake.set()
        if self._thread.ident != threading.get_ident():
            self._thread.join(timeout=1.0)
        with self._lock:
            self._newest = None

    def _copy_of_newest(self) -> Any:
        Gst = gst()
        with self._lock:
            newest = self._newest
        if newest is None or newest.pts == Gst.CLOCK_TIME_NONE:
            return None
        flags = Gst.BufferCopyFlags(0)
        for name in _COPY_FLAGS_NAMES:
            flags |= getattr(Gst.BufferCopyFlags, name)
        copy = newest.copy_region(flags, 0, newest.get_size())
        copy.pts = newest.pts + INJECTED_PTS_STEP_NS
        copy.dts = Gst.CLOCK_TIME_NONE
        return copy

    def _run(self) -> None:
        while True:
            self._wake.wait()
            self._wake.clear()
            if self._closing:
                return
            copy = self._copy_of_newest()
            if copy is None:
                continue
            # The pad's stream lock orders it with the camera's frames; the encoder's input
            # probe forces it to a keyframe, or drops it (the request was answered already).
            self._pad.chain(copy)
