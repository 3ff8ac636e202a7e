"""The picture back right after a blackout: the sender answers a keyframe request with the
newest frame encoded again at once (not with the camera's next capture), and the receiver
gives up the silence's packets instead of holding the keyframe behind their repair."""

from __future__ import annotations

import asyncio
import threading
from dataclasses import dataclass

import pytest
from conftest import free_udp_port, wait_until
from lossy_udp import LossyRelay
from support.video_link import video_link

from brasidas.media import video
from brasidas.media.keyframes import KeyframeClock
from brasidas.media.repair import DEFAULT_DROPOUT_MS
from brasidas.media.video import VideoOut, VideoSettings


@dataclass(frozen=True)
class _AccessUnit:
    keyframe: bool
    captured_ns: int


class _Encoded:
    """The encoded stream as sent (the recorder's tap): each access unit's kind and the
    capture time of the picture it holds."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.units: list[_AccessUnit] = []

    def __call__(self, annex_b: bytes, keyframe: bool, captured_ns: int) -> None:
        with self._lock:
            self.units.append(_AccessUnit(keyframe, captured_ns))

    def since(self, start: int) -> list[_AccessUnit]:
        with self._lock:
            return self.units[start:]

    def count(self) -> int:
        with self._lock:
            return len(self.units)


def test_a_request_is_answered_now_only_once_its_gap_is_over() -> None:
    clock = KeyframeClock(30, min_request_gap_s=0.25)
    assert clock.on_frame(0.0)
    assert not clock.answers_now(0.01)  # nothing asked
    clock.request(0.02)
    assert clock.answers_now(0.02)
    assert clock.on_frame(0.021)  # the frame encoded at once answers it
    assert not clock.answers_now(0.03)
    clock.request(0.1)  # 80 ms after the last one asked: deferred to the gap's end
    assert not clock.answers_now(0.1)
    assert clock.answers_now(0.28)


async def _just_after_a_frame(log: _Encoded) -> int:
    """Wait for the next access unit; returns how many there are then."""
    count = log.count()
    await wait_until(lambda: log.count() > count, timeout=10)
    return log.count()


async def test_a_keyframe_request_is_answered_by_the_newest_frame_encoded_at_once() -> None:
    log = _Encoded()
    # 2 fps: the camera's next frame is 500 ms away when the request comes.
    settings = VideoSettings(test_source=True, port=free_udp_port(), framerate=2)
    stream = VideoOut("navcam", settings)
    stream.access_unit_sinks.append(log)
    try:
        await stream.start()
        await wait_until(lambda: log.count() >= 3, timeout=10)
        start = await _just_after_a_frame(log)
        newest = log.since(start - 1)[0]
        assert not newest.keyframe
        stream.request_keyframe()
        await wait_until(lambda: log.count() > start, timeout=10)
        answer = log.since(start)[0]
        # The very next access unit is the keyframe, of the same picture as the frame before
        # it (its capture time): encoded at once, not at the camera's next capture.
        assert answer.keyframe
        assert answer.captured_ns == newest.captured_ns
        assert stream.describe()["keyframes_at_once"] == 1

        # On a congested link the copy would only add to the queue: the camera's next frame
        # answers, as before.
        stream.keyframes.congested = True
        await asyncio.sleep(0.3)  # the rate limit's gap since the last keyframe asked
        start = await _just_after_a_frame(log)
        newest = log.since(start - 1)[0]
        stream.request_keyframe()
        await wait_until(lambda: log.count() > start, timeout=10)
        answer = log.since(start)[0]
        assert answer.keyframe
        assert answer.captured_ns > newest.captured_ns
        assert stream.describe()["keyframes_at_once"] == 1
    finally:
        await stream.stop()


class _Blackout(LossyRelay):
    """A loopback UDP relay that loses everything while ``cut``."""

    def __init__(self, to: tuple[str, int]) -> None:
        self.cut = False  # before the relay's thread starts
        super().__init__(to, loss=0.0)

    def lost(self, data: bytes) -> bool:
        return self.cut


async def test_after_a_blackout_beyond_repair_its_packets_are_not_asked_for_again() -> None:
    async with video_link(_Blackout, _Blackout, pattern="smpte") as link:
        receiver, media, feedback = link.receiver, link.media, link.feedback
        assert feedback is not None
        await wait_until(lambda: receiver.frames >= 30, timeout=20)
        assert receiver.repairs is not None
        before = receiver.repairs.counters()
        frames = receiver.frames
        media.cut = feedback.cut = True
        await asyncio.sleep(0.4)  # ~10 frames, ~50 packets: past the repair's 200 ms
        media.cut = feedback.cut = False
        await wait_until(lambda: receiver.frames >= frames + 30, timeout=20)
        after = receiver.repairs.counters()
        # A keyframe was asked at the first packet after the silence, and none of the
        # silence's packets: no decoder could use them. (The jitter buffer asked for the last
        # 200 ms of them, ~40, and let the keyframe out only once they had come.)
        assert after.keyframes_after_silence == before.keyframes_after_silence + 1, after
        assert after.retransmission_requests - before.retransmission_requests < 5, after
        # Its own settings back for the next gap (a lost packet is asked for again).
        jitterbuffer = receiver.repairs.jitterbuffers[0]
        assert jitterbuffer.get_property("max-dropout-time") == DEFAULT_DROPOUT_MS
        assert jitterbuffer.get_property("faststart-min-packets") == 0


RTCP_PSFB = 206
PLI_FMT = 1
FIR_FMT = 4


def _asks_keyframe(rtcp: bytes) -> bool:
    """A (compound or reduced-size) RTCP packet holding a PLI or a FIR (RFC 4585, 5104)."""
    offset = 0
    while offset + 4 <= len(rtcp):
        if rtcp[offset + 1] == RTCP_PSFB and rtcp[offset] & 0x1F in (PLI_FMT, FIR_FMT):
            return True
        offset += (int.from_bytes(rtcp[offset + 2 : offset + 4], "big") + 1) * 4
    return False


class _BlackoutLosingAnAsk(_Blackout):
    """Cut while ``cut``; and loses the next keyframe request after ``lose_next_ask`` is set."""

    def __init__(self, to: tuple[str, int]) -> None:
        self.lose_next_ask = False
        self.asks_lost = 0
        self.asks_passed = 0
        super().__init__(to)

    def lost(self, data: bytes) -> bool:
        if self.cut:
            return True
        if _asks_keyframe(data):
            if self.lose_next_ask:
                self.lose_next_ask = False
                self.asks_lost += 1
                return True
            self.asks_passed += 1
        return False


async def test_a_keyframe_request_lost_after_a_blackout_is_asked_again(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A request is one RTCP packet: lost (1 in 20 at 5 % loss) after a blackout, nothing else
    asked (the depayloader's own request is held behind it) and the picture stayed broken to
    the encoder's next periodic keyframe. Not answered in KEYFRAME_ANSWER_S, it is asked
    again. The sender's periodic keyframes are put off here (a minute), so that only a
    request can bring the picture back (and the bitrate's drain pause off)."""
    monkeypatch.setattr(video, "ENCODER_GOP_S", 60)  # the encoder's own backstop too
    async with video_link(_Blackout, _BlackoutLosingAnAsk, pattern="smpte") as link:
        receiver, sender, media, feedback = link.receiver, link.sender, link.media, link.feedback
        assert feedback is not None
        # Nor does the bitrate adapt: the blackout's feedback silence may end in a drain
        # pause, and the keyframe it ends with would bring the picture back first.
        monkeypatch.setattr(sender, "adapt_bitrate", lambda now: None)
        with sender._keyframes_lock:
            sender.keyframes.interval_s = 60.0
            sender.keyframes.set_framerate(sender.settings.framerate)
        await wait_until(lambda: receiver.frames >= 30, timeout=20)
        assert receiver.repairs is not None
        await wait_until(lambda: not receiver.repairs.counters().keyframe_owed, timeout=10)
        before = receiver.repairs.counters()
        asked = sender.describe()["keyframes_requested"]
        media.cut = feedback.cut = True
        feedback.lose_next_ask = True
        await asyncio.sleep(0.4)  # past the repair's 200 ms
        frames = receiver.frames
        media.cut = feedback.cut = False
        await wait_until(lambda: feedback.asks_lost == 1, timeout=10)

        def state() -> str:
            assert receiver.repairs is not None
            return (
                f"{receiver.repairs.counters()}, asks passed {feedback.asks_passed}, sender "
                f"{ {k: v for k, v in sender.describe().items() if 'keyframe' in k} }"
            )

        # The picture back within a second (the keyframe asked again), not a minute on.
        try:
            await wait_until(lambda: receiver.frames >= frames + 5, timeout=5)
        except TimeoutError:
            raise AssertionError(f"no picture 5 s after the blackout: {state()}") from None
        assert sender.describe()["keyframes_requested"] > asked, state()
        after = receiver.repairs.counters()
        assert after.keyframes_after_silence == before.keyframes_after_silence + 1, after
        assert after.keyframes_asked_again >= before.keyframes_asked_again + 1, after
        assert after.keyframes_asked_again <= before.keyframes_asked_again + 3, after
        await wait_until(lambda: not receiver.repairs.counters().keyframe_owed, timeout=5)
