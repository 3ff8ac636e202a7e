"""Keyframes: the interval follows live framerate changes; a request makes the next frame one."""

from __future__ import annotations

import asyncio
import itertools
import threading

import pytest
from conftest import free_udp_port, wait_until

from brasidas.media.gst import has_element
from brasidas.media.keyframes import KeyframeClock
from brasidas.media.video import VideoOut, VideoSettings


def test_the_first_frame_after_a_drain_pause_is_a_keyframe_whatever_the_gap() -> None:
    clock = KeyframeClock(30, min_request_gap_s=0.25)
    clock.congested = True  # a drain pause comes with a capacity drop: keyframes are queued
    assert clock.on_frame(0.0)
    assert not clock.on_frame(0.1)
    # 0.1 s after the last keyframe a request waits out the gap; a resume does not.
    clock.request(0.1)
    assert not clock.on_frame(0.15)
    assert clock.on_frame(0.2, resume=True)
    assert clock.counters.resumed == 1
    assert not clock.on_frame(0.24)  # the pending request was answered by it


def test_the_interval_follows_the_framerate_and_requests_are_rate_limited() -> None:
    clock = KeyframeClock(30, min_request_gap_s=0.25)
    assert clock.on_frame(0.0)  # the first frame starts the stream
    frames = [clock.on_frame(i / 30) for i in range(1, 61)]
    assert [i + 1 for i, key in enumerate(frames) if key] == [30, 60]
    clock.set_framerate(5)
    keys = [i for i in range(1, 16) if clock.on_frame(2 + i / 5)]
    assert keys == [5, 10, 15]
    clock.request(5.5)
    assert clock.on_frame(5.5)  # answered on the next frame
    assert not clock.on_frame(5.7)  # the periodic count restarted at the forced one
    # A keyframe 0.1 s ago: the request waits out the gap, then is answered (the receiver
    # may have lost that keyframe: dropped, the request left it frozen a second).
    clock.request(5.6)
    clock.request(5.65)  # the same wait: one keyframe answers both
    assert not clock.on_frame(5.7)
    assert clock.on_frame(5.76)
    assert not clock.on_frame(5.9)
    assert clock.counters.requested == 2
    assert clock.counters.deferred == 1


def test_a_periodic_keyframe_does_not_hold_a_request_back() -> None:
    """After a blackout the periodic keyframe made during it was lost with it: the receiver's
    request is answered on the next frame, not 250 ms after that keyframe."""
    clock = KeyframeClock(30, min_request_gap_s=0.25)
    assert clock.on_frame(0.0)
    periodic = [i for i in range(1, 31) if clock.on_frame(i / 30)]
    assert periodic == [30]  # at 1.0 s, into the blackout
    clock.request(1.1)  # the link is back: the receiver asks
    assert clock.on_frame(1.1 + 1 / 30)
    assert clock.counters.deferred == 0
    # Requests still count against each other: the next one within 250 ms waits.
    clock.request(1.2)
    assert not clock.on_frame(1.2)
    assert clock.on_frame(1.14 + 0.25)
    assert clock.counters.deferred == 1
    # On a congested link the periodic keyframe is queued, not lost: a request soon after it
    # waits the gap out, as two keyframes 250 ms apart at most would refill the queue.
    clock.congested = True
    periodic = [i for i in range(1, 31) if clock.on_frame(1.39 + i / 30)]
    assert periodic == [30]  # at 2.39 s
    clock.request(2.45)
    assert not clock.on_frame(2.45)
    assert clock.on_frame(2.39 + 0.26)


class _KeyframeLog:
    """The encoded stream as sent: one flag per access unit, True for keyframes."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.flags: list[bool] = []

    def __call__(self, annex_b: bytes, keyframe: bool, captured_ns: int) -> None:
        with self._lock:
            self.flags.append(keyframe)

    def since(self, start: int) -> list[bool]:
        with self._lock:
            return self.flags[start:]


def gaps(flags: list[bool]) -> list[int]:
    """Frames from one keyframe to the next."""
    at = [i for i, key in enumerate(flags) if key]
    return [b - a for a, b in itertools.pairwise(at)]


@pytest.mark.parametrize("encoder", ["x264enc", "openh264enc"])
async def test_keyframe_interval_follows_live_framerate_changes(encoder: str) -> None:
    if not has_element(encoder):
        pytest.skip(f"{encoder} is not installed")
    log = _KeyframeLog()
    settings = VideoSettings(test_source=True, port=free_udp_port(), encoder=encoder)
    stream = VideoOut("navcam", settings)
    stream.access_unit_sinks.append(log)
    try:
        await stream.start()
        await wait_until(lambda: len(log.since(0)) >= 70, timeout=10)
        assert set(gaps(log.since(0))) == {30}  # a keyframe a second at 30 fps

        stream.set_framerate(5)
        await asyncio.sleep(0.3)  # frames already encoded at 30 fps
        start = len(log.since(0))
        await wait_until(lambda: sum(log.since(start)) >= 3, timeout=10)
        assert set(gaps(log.since(start))) == {5}  # still one a second, not every 6 s

        stream.set_framerate(30)
        await asyncio.sleep(0.5)
        start = len(log.since(0))
        await wait_until(lambda: sum(log.since(start)) >= 3, timeout=10)
        assert set(gaps(log.since(start))) == {30}  # not every 0.17 s
    finally:
        await stream.stop()


async def test_a_keyframe_request_makes_the_next_frame_a_keyframe() -> None:
    log = _KeyframeLog()
    stream = VideoOut("navcam", VideoSettings(test_source=True, port=free_udp_port()))
    stream.access_unit_sinks.append(log)
    try:
        await stream.start()
        await wait_until(lambda: len(log.since(0)) >= 10, timeout=10)
        start = len(log.since(0))
        stream.request_keyframe()
        await wait_until(lambda: len(log.since(start)) >= 3, timeout=5)
        # The frame in the encoder when asked may still be a delta; the one after is key.
        assert any(log.since(start)[:2])
        assert stream.describe()["keyframes_requested"] == 1
    finally:
        await stream.stop()
