"""New caps for a running pipeline's capsfilters, set on its streaming thread between frames.

A capsfilter reads its ``caps`` property twice in one caps query: once on the way downstream
and once on the answer's way back. Set from another thread (the event loop) while the
streaming thread is inside such a query, the two halves disagree (framerate 30 out, 15 back),
the answer is empty and the camera's source stops with "not-negotiated": the stream fails and
is rebuilt. Two framerate changes in a row (the override's 30 fps, then ``navcam=15``) did it
under load: the second landed inside the renegotiation the first had started. Every query
that runs on the streaming thread is between two buffers there, so new caps set from a probe
on that thread's path never land inside one.
"""

from __future__ import annotations

import threading
from typing import Any

from brasidas.media.gst import caps, gst


class StreamingThreadCaps:
    """The caps wanted for each capsfilter of one pipeline, applied by the streaming thread
    at its next buffer through :meth:`watch`'s pad. ``want`` from any thread; a pipeline that
    does not flow (paused) gets them when it flows again. One per pipeline."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._wanted: dict[str, tuple[Any, str]] = {}
        """Element name → (capsfilter, caps text), the newest for each filter."""

    def want(self, capsfilter: Any, text: str) -> None:
        """Any thread: ``capsfilter`` is to have the caps ``text`` from the next buffer on."""
        with self._lock:
            self._wanted[capsfilter.get_name()] = (capsfilter, text)

    @property
    def pending(self) -> int:
        """Caps wanted and not yet applied."""
        with self._lock:
            return len(self._wanted)

    def watch(self, pad: Any) -> None:
        """Apply the wanted caps on the thread that pushes buffers through ``pad`` (upstream
        of every filter this pipeline changes, on the same streaming thread)."""
        pad.add_probe(gst().PadProbeType.BUFFER, _apply_probe, self)

    def apply(self) -> None:
        """Streaming thread: set the wanted caps (each filter then asks upstream to
        renegotiate, which this thread does before its next buffer)."""
        with self._lock:
            if not self._wanted:
                return
            wanted, self._wanted = list(self._wanted.values()), {}
        for capsfilter, text in wanted:
            capsfilter.set_property("caps", caps(text))


def _apply_probe(pad: Any, info: Any, streaming_caps: StreamingThreadCaps) -> Any:
    streaming_caps.apply()
    return gst().PadProbeReturn.OK
