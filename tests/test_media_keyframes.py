"""Keyframes: the interval follows live framerate changes; a request makes the next frame one."""

from __future__ import annotations

import asyncio
import itertools
import threading

import pytest
from conftest import free_udp_port, wait_until

from brasidas.media.gst import has_element
from brasidas.media.keyframes import KeyframeClock
from brasidas.media.repair import (
    KEYFRAME_ANSWER_S,
    KEYFRAME_ASKS_AGAIN_MAX,
    REPAIR_LATENCY_MS,
    KeyframeOwed,
    SilenceWatch,
)
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


def test_a_keyframe_not_come_is_asked_again_a_bounded_number_of_times() -> None:
    owed = KeyframeOwed()
    assert not owed.ask_again(0.0)  # nothing asked
    owed.asked(1.0)
    assert not owed.ask_again(1.0 + KEYFRAME_ANSWER_S - 0.01)  # its answer may still come
    assert owed.ask_again(1.0 + KEYFRAME_ANSWER_S)
    assert not owed.ask_again(1.0 + KEYFRAME_ANSWER_S + 0.01)  # the next wait starts now
    # Asked again by the depayloader meanwhile: the wait starts again, the budget stays.
    owed.asked(2.0)
    at = 2.0
    for _ in range(KEYFRAME_ASKS_AGAIN_MAX - 1):
        at += KEYFRAME_ANSWER_S
        assert owed.ask_again(at)
    assert not owed.ask_again(at + KEYFRAME_ANSWER_S)  # given up: the periodic one comes
    assert owed.due is None and owed.asked_again == KEYFRAME_ASKS_AGAIN_MAX
    # A keyframe pays what is owed: nothing is asked again.
    owed.asked(10.0)
    owed.arrived()
    assert not owed.ask_again(20.0)
    assert owed.asked_again == KEYFRAME_ASKS_AGAIN_MAX


def _frames(watch: SilenceWatch, seq: int, ts: int, at: float, count: int, fps: int) -> int:
    """``count`` frames of 3 packets each from ``at`` (s): asks nothing on a clean stream."""
    for frame in range(count):
        for packet in range(3):
            now = at + frame / fps + packet * 0.0005
            assert not watch.on_packet(seq & 0xFFFF, ts + frame * 90000 // fps, now)
            seq += 1
    return seq


def test_a_keyframe_is_asked_at_the_first_packet_after_a_silence_past_the_deadline() -> None:
    watch = SilenceWatch()
    seq = _frames(watch, 65530, 1000, 0.0, 10, 30)  # the sequence wraps on the way
    last_arrival = 9 / 30 + 0.001
    # A 300 ms blackout at 30 fps: the first frame skipped was due a frame after the silence
    # began; its deadline (+ REPAIR_LATENCY_MS) has passed when the link is back. The first
    # packet after it asks, before any repair could arrive (nor would a repair show a frame).
    back = last_arrival + 0.3
    assert back > last_arrival + 1 / 30 + REPAIR_LATENCY_MS / 1000
    assert watch.on_packet((seq + 27) & 0xFFFF, 1000 + 19 * 3000, back)
    # Once: the packets after it are contiguous again.
    assert not watch.on_packet((seq + 28) & 0xFFFF, 1000 + 19 * 3000, back + 0.0005)
    # A retransmission or a reordered packet (older) asks nothing either.
    assert not watch.on_packet((seq + 5) & 0xFFFF, 1000 + 11 * 3000, back + 0.001)


def test_a_silence_repaired_in_time_asks_no_keyframe() -> None:
    watch = SilenceWatch()
    seq = _frames(watch, 100, 0, 0.0, 10, 30)
    # A 100 ms blackout at 30 fps: three frames skipped, all within their deadline.
    assert not watch.on_packet(seq + 9, 13 * 3000, 9 / 30 + 0.1)
    # At 5 fps a lost packet (even a whole frame's tail) shows only 200 ms on: no frame is
    # skipped, the repair is in time.
    slow = SilenceWatch()
    seq = _frames(slow, 0, 0, 0.0, 5, 5)
    assert not slow.on_packet(seq + 1, 5 * 18000, 1.0)
    # Two frames skipped at 5 fps (400 ms): the first one's deadline has passed.
    assert slow.on_packet(seq + 8, 8 * 18000, 4 / 5 + 0.6)


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
