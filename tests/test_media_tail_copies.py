"""A low framerate's frames end with their last packet sent twice: a lost last packet shows
at the receiver only when the next frame's first arrives (at 5 fps, 200 ms on), so without
the copy its frame came a frame late."""

from __future__ import annotations

import statistics

from conftest import free_udp_port, wait_until
from lossy_udp import LossyRelay

from brasidas.media.repair import LossyLink
from brasidas.media.video import PAYLOAD_TYPE, VideoIn, VideoOut, VideoSettings


class _FirstTailLost(LossyRelay):
    """A loopback UDP relay that loses the first copy of every frame's last packet (RTP
    marker set): the worst case of a lossy link, made certain."""

    def __init__(self, to: tuple[str, int]) -> None:
        self._seen: set[int] = set()  # before the relay's thread starts
        super().__init__(to, loss=0.0)

    def lost(self, data: bytes) -> bool:
        if len(data) < 4 or data[1] != 0x80 | PAYLOAD_TYPE:
            return False
        seq = int.from_bytes(data[2:4], "big")
        if seq in self._seen:
            return False
        self._seen.add(seq)
        return True


async def test_at_5_fps_a_frame_whose_last_packet_is_lost_still_comes_on_time() -> None:
    port = free_udp_port()
    receiver = VideoIn("rx", host="127.0.0.1", port=port)
    await receiver.start()
    relay = _FirstTailLost(("127.0.0.1", port))
    settings = VideoSettings(
        test_source=True, host="127.0.0.1", port=relay.port, framerate=5, pattern="smpte"
    )
    sender = VideoOut("navcam", settings)
    try:
        await sender.start()
        assert sender.feedback is not None
        receiver.set_feedback("127.0.0.1", sender.feedback.port)  # it may ask (NACK) too
        await wait_until(lambda: receiver.stamped >= 15, timeout=30)
        assert relay.dropped >= 15  # every frame lost its last packet once
        assert sender.describe()["tail_copies"] >= 15
        # Each frame complete as it was sent. Without the copy each waited for the next
        # frame to show the loss, then for its repair: a median over 200 ms at 5 fps.
        latencies = list(receiver.latencies)[5:]
        assert statistics.median(latencies) < 100, latencies
    finally:
        await sender.stop()
        await receiver.stop()
        relay.close()


async def test_at_30_fps_no_copies_are_sent() -> None:
    port = free_udp_port()
    receiver = VideoIn("rx", host="127.0.0.1", port=port)
    await receiver.start()
    sender = VideoOut("navcam", VideoSettings(test_source=True, host="127.0.0.1", port=port))
    try:
        await sender.start()
        await wait_until(lambda: receiver.frames >= 30, timeout=20)
        # The next frame is 33 ms away: a lost last packet shows soon enough.
        assert sender.describe()["tail_copies"] == 0
        # Live changes of the framerate take the copies on and off (the copying is on the
        # pad only while wanted: at 30 fps every packet would take the GIL for nothing).
        sender.set_framerate(5)
        await wait_until(lambda: sender.describe()["tail_copies"] >= 3, timeout=20)
        sender.set_framerate(30)
        copied = sender.describe()["tail_copies"]
        frames = receiver.frames
        await wait_until(lambda: receiver.frames >= frames + 30, timeout=20)
        assert sender.describe()["tail_copies"] == copied
    finally:
        await sender.stop()
        await receiver.stop()


def test_a_lossy_link_turns_the_copies_on_at_any_framerate_and_a_clean_one_off() -> None:
    tails = LossyLink()
    assert not tails.update(0, 65000, 0.0)
    # 190 packets a second (30 fps), 10 % of them asked for again: a lossy link.
    assert tails.update(19, (65000 + 190) & 0xFFFF, 1.0)  # the sequence wraps on the way
    # 2 % asked for: still on (it turns off below 1 %, not at the threshold it came on at).
    assert tails.update(23, (65000 + 380) & 0xFFFF, 2.0)
    assert not tails.update(24, (65000 + 570) & 0xFFFF, 3.0)
    # 2 % does not turn them on either.
    assert not tails.update(28, (65000 + 760) & 0xFFFF, 4.0)


async def test_at_30_fps_a_lossy_link_gets_the_copies() -> None:
    port = free_udp_port()
    receiver = VideoIn("rx", host="127.0.0.1", port=port)
    await receiver.start()
    relay = LossyRelay(("127.0.0.1", port), loss=0.1, seed=3)
    sender = VideoOut(
        "navcam",
        VideoSettings(test_source=True, host="127.0.0.1", port=relay.port, framerate=30),
    )
    try:
        await sender.start()
        assert sender.feedback is not None
        receiver.set_feedback("127.0.0.1", sender.feedback.port)
        # The receiver asks for a tenth of the packets again: the sender copies each frame's
        # last packet, which would otherwise show missing only with the next frame.
        await wait_until(lambda: sender.tail_copies_sent() >= 30, timeout=30)
        assert sender.lossy_link.on
    finally:
        await sender.stop()
        await receiver.stop()
        relay.close()
