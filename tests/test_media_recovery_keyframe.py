"""The keyframe a drain pause ends with is made at the lowered bitrate (real x264 pipeline).

At a capacity drop the sender pauses its frames while the link's queue drains, then restarts
the picture with a keyframe: every ms that keyframe takes to cross the slower link is picture
frozen. With x264's usual rate-control buffer it was made at what the buffer still allowed
(5.7 kB at the cut to 450 kbit/s: ~100 ms of a 500 kbit/s link).
"""

from __future__ import annotations

import threading
import time
import weakref

from conftest import free_udp_port, wait_until

from brasidas.media.gst import gst
from brasidas.media.twcc import QueueOveruse
from brasidas.media.video import (
    X264_RECOVERY_VBV_MS,
    X264_VBV_MS,
    VideoOut,
    VideoSettings,
    _thinning_probe,
)

CUT_KBPS = 450
"""Where the pause's deep cut takes the 1.5 Mbit/s ceiling (0.3x)."""


async def test_the_keyframe_after_a_drain_pause_is_small_for_the_lowered_bitrate() -> None:
    lock = threading.Lock()
    units: list[tuple[int, bool, int]] = []

    def on_unit(annex_b: bytes, keyframe: bool, captured_ns: int) -> None:
        with lock:
            units.append((len(annex_b), keyframe, captured_ns))

    settings = VideoSettings(
        test_source=True,
        host="127.0.0.1",
        port=free_udp_port(),
        encoder="x264enc",
        pattern="smpte",
        motion=4,
    )
    stream = VideoOut("navcam", settings)
    stream.access_unit_sinks.append(on_unit)
    try:
        await stream.start()
        # A second and a half at 1.5 Mbit/s: frames of ~6 kB, the rate control settled.
        await wait_until(lambda: len(units) >= 45, timeout=15)
        paused_ns = time.time_ns()
        now = time.monotonic()
        # The link's queue seen packet by packet, confirmed: pause, cut to 0.3x.
        stream._queue_overuse = QueueOveruse(
            queue_ms=50, capacity_kbps=550, sent_kbps=1500, at=now, newest_sent_at=now
        )
        assert stream.adapt_bitrate(now) == CUT_KBPS
        assert stream.describe()["drain_pauses"] == 1

        def after_pause() -> list[tuple[int, bool]]:
            with lock:
                return [(size, key) for size, key, at in units if at > paused_ns]

        await wait_until(lambda: len(after_pause()) >= 10, timeout=15)
        frames = after_pause()
        with lock:
            before = [size for size, key, at in units[15:] if at <= paused_ns and not key]
        size, keyframe = frames[0]
        assert keyframe, frames  # the picture restarts at a keyframe made after the pause
        # ~2 kB: 35 ms of a 500 kbit/s link (5.7 kB before: the frames before the pause
        # were ~6.3 kB each).
        assert size < 3000, (frames, before[-5:])
        assert min(before) > 2 * size, (frames, before[-5:])
        # The short buffer lasts while the bitrate is held, then the usual one returns.
        encoder = stream.pipeline.get_by_name("encoder") if stream.pipeline else None
        assert encoder is not None
        assert encoder.get_property("vbv-buf-capacity") == X264_RECOVERY_VBV_MS
        stream.adapt_bitrate(stream.budget.enforced_until + 0.1)
        assert encoder.get_property("vbv-buf-capacity") == X264_VBV_MS
    finally:
        await stream.stop()


def test_the_thinning_lets_the_frame_that_ends_a_drain_pause_through() -> None:
    Gst = gst()
    stream = VideoOut("navcam", VideoSettings())
    stream.thinning = 2  # the link forced the bitrate down: one frame in two is encoded

    def passes() -> bool:
        # The probe reads only the stream (the pad and the buffer are not looked at).
        verdict = _thinning_probe(None, None, weakref.ref(stream))
        return bool(verdict == Gst.PadProbeReturn.OK)

    # The pause ended: the next camera frame is its keyframe, whatever the thinning's cadence
    # (it would have dropped this one: a frame, 33 ms, more of a frozen picture).
    stream.keyframe_after_pause = True
    assert passes()
    stream.keyframe_after_pause = False  # the keyframe probe took it
    # The cadence starts from it: one in two after.
    assert [passes() for _ in range(4)] == [False, True, False, True]
