"""The speed cap reads the picture's age (issue 28): a frozen picture counts as latency."""

from __future__ import annotations

import time
from types import SimpleNamespace
from typing import Any

from brasidas.config.platform import SafetySection
from brasidas.media.pipeline import StreamState
from brasidas.media.video import VideoIn
from platformd.speedcap import compute_cap
from stationd.console.media import PageLatency
from stationd.video_feed import AccessUnit, FanOut


def _unit(arrival_ms: float, keyframe: bool = True) -> AccessUnit:
    return AccessUnit(b"\x00\x00\x00\x01\x65", keyframe, arrival_ms - 10, arrival_ms)


def test_a_frozen_feed_ages_the_pages_latency_and_the_cap_falls_within_a_second() -> None:
    safety = SafetySection()
    fanout = FanOut()
    feed = SimpleNamespace(fanout=fanout)
    hub: Any = SimpleNamespace(page_latency={}, feeds={("rover", "navcam"): feed})
    latency = PageLatency(hub, "rover", None)
    now_ms = time.time() * 1000
    fanout.feed(_unit(now_ms))
    hub.page_latency["rover"] = (20.0, time.monotonic())
    assert 20.0 <= (latency() or 0) < 20.0 + 500  # fresh: the page's own figure

    # The picture froze a second ago (no frame since): its age is the latency now, although
    # the page's last report (of the frames it did show) was 20 ms.
    fanout.feed(_unit(now_ms - 1000))
    aged = latency()
    assert aged is not None
    assert aged >= 1020
    worst = compute_cap(safety, 6.0, None, None).cap_kmh
    assert compute_cap(safety, 6.0, aged, 0).cap_kmh <= worst
    # The page stopped reporting long ago: the frozen feed still counts, it is not forgotten.
    hub.page_latency["rover"] = (20.0, time.monotonic() - 60)
    assert (latency() or 0) >= 1020


def test_a_feed_frozen_after_a_gap_keeps_its_last_shown_time() -> None:
    fanout = FanOut()
    assert fanout.staleness_ms(1000.0) is None
    fanout.feed(_unit(1000.0))
    fanout.feed(_unit(1100.0, keyframe=False))
    fanout.feed(AccessUnit(b"x", False, 1190.0, 1200.0, after_gap=True))  # held, not shown
    assert fanout.staleness_ms(1500.0) == 400.0


def test_the_receivers_latency_is_the_age_of_its_picture() -> None:
    receiver = VideoIn("rx", port=1)
    receiver.state = StreamState.PLAYING
    receiver.latencies.extend([10.0, 12.0, 14.0])
    receiver.last_frame_at = 100.0
    assert receiver.recent_latency_ms(now=100.0) == 12.0
    assert receiver.recent_latency_ms(now=101.5) == 1512.0
