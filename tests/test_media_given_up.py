"""Packets the sender gave up at a drain pause: answered without their media, lost at once.

After a capacity drop the sender pauses, then restarts the picture with a keyframe; the
packets the full queue dropped before it are of frames no decoder can use. Their
retransmissions used to be dropped, and the receiver's jitter buffer held the keyframe behind
them for its whole repair budget (100-200 ms, traced at the 2 → 0.5 Mbit/s drop).
"""

from __future__ import annotations

import asyncio
import time

from conftest import wait_until
from lossy_udp import LossyRelay
from support.video_link import video_link

from brasidas.media.video import (
    GIVEN_UP_PAYLOAD,
    emptied_retransmission,
)


def _rtx_packet(*, padding: bool) -> bytes:
    """An RTX packet as rtprtxsend makes it: one-byte header extensions (NTP-64, TWCC),
    the original sequence number, the media, and optionally RTP padding."""
    first = 0x80 | 0x10 | (0x20 if padding else 0)
    header = bytes([first, 97]) + (4321).to_bytes(2, "big") + bytes(8)
    extensions = bytes([0xBE, 0xDE, 0, 3]) + bytes([0x17]) + bytes(8) + bytes([0x21, 0, 7])
    original_seq = (65530).to_bytes(2, "big")
    media = bytes([0x7C, 0x85]) + bytes(1000)
    return header + extensions + original_seq + media + (bytes([0, 0, 3]) if padding else b"")


def test_a_given_up_retransmission_keeps_its_header_and_original_number_only() -> None:
    for padding in (False, True):
        packet = _rtx_packet(padding=padding)
        emptied = emptied_retransmission(packet[:64], len(packet))
        assert emptied is not None
        # 12 header + 16 extensions + 2 original sequence number, then the mark.
        assert emptied[:1] == bytes([0x90])  # the padding bit cleared with the padding
        assert emptied[1:30] == packet[1:30]
        assert emptied[28:30] == (65530).to_bytes(2, "big")
        assert emptied[30:] == GIVEN_UP_PAYLOAD
        # Already given up (on its way out), or a header not read whole: left alone.
        assert emptied_retransmission(emptied, len(emptied)) is None
        assert emptied_retransmission(packet[:20], len(packet)) is None


async def test_packets_given_up_are_lost_at_once_at_the_receiver_and_the_picture_goes_on() -> None:
    def lossy(to: tuple[str, int]) -> LossyRelay:
        return LossyRelay(to, loss=0.05, seed=3)

    async with video_link(lossy, encoder="x264enc", pattern="smpte", motion=4) as link:
        sender, receiver = link.sender, link.receiver
        assert sender.pipeline is not None
        await wait_until(lambda: receiver.frames >= 30, timeout=20)
        # As after a drain pause: every packet sent so far and for a while yet is stale.
        pay = sender.pipeline.get_by_name("pay")
        sender.stale_before = (int(pay.get_property("seqnum")) + 30000) & 0xFFFF
        sender.stale_until = time.monotonic() + 60
        with sender._adapt_lock:
            sender._drop_retransmissions(True)
        frames = receiver.frames
        await wait_until(lambda: receiver.given_up >= 3, timeout=20)
        # Answered, not dropped: the receiver took each for lost, without its repair budget.
        assert sender.retransmissions_emptied >= receiver.given_up
        assert sender.retransmissions_dropped == 0
        stats = receiver.describe()
        assert stats["packets_given_up"] == receiver.given_up
        # The keyframe follows what the sender gave up: the depayloader's own request at such
        # a loss is held, not sent (it made a second keyframe on the just-drained link).
        assert stats["repair"]["keyframe_requests_held"] >= 1, stats["repair"]
        # No picture was made of them, and the stream goes on (keyframes asked as for a loss;
        # rtph264depay crashed the receiver on an empty payload).
        await wait_until(lambda: receiver.frames >= frames + 30, timeout=20)
        await asyncio.sleep(0)
