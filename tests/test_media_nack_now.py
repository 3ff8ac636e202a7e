"""A missing packet is asked for the moment its gap arrives, by the receiver's own NACK: once
on a clean link, twice on a lossy one (the jitter buffer's own first ask is the copy)."""

from __future__ import annotations

import statistics
import time

from conftest import wait_until
from support.rtcp import DropEvery, NackLog, nacked
from support.video_link import video_link

from brasidas.media.nack import NACK_GAP_MAX, GapWatch, generic_nack
from brasidas.media.repair import RTX_RETRY_MIN_MS, RepairCounters

SSRC = 0x1234_5678


def test_the_nack_names_each_missing_packet_in_as_few_entries_as_it_can() -> None:
    assert nacked(generic_nack(7, SSRC, [5])) == [5]
    run = list(range(100, 117))  # a packet id and the 16 after it: one entry
    packet = generic_nack(7, SSRC, run)
    assert len(packet) == 12 + 4 and nacked(packet) == run
    # RTPFB, generic NACK; length in words minus one; the sender's SSRC, then the media's.
    assert packet[0] == 0x81 and packet[1] == 205
    assert int.from_bytes(packet[2:4], "big") == len(packet) // 4 - 1
    assert packet[4:12] == (7).to_bytes(4, "big") + SSRC.to_bytes(4, "big")
    assert nacked(generic_nack(7, SSRC, [*run, 117])) == [*run, 117]
    assert len(generic_nack(7, SSRC, [*run, 117])) == 12 + 8
    across = [65534, 65535, 0, 1]
    assert nacked(generic_nack(7, SSRC, across)) == across
    assert nacked(generic_nack(7, SSRC, [3, 40])) == [3, 40]


def test_the_gap_watch_names_the_packets_missing_before_each_arrival() -> None:
    gaps = GapWatch()
    assert gaps.on_packet(SSRC, 10) == []
    assert gaps.on_packet(SSRC, 11) == []
    assert gaps.on_packet(SSRC, 14) == [12, 13]
    # A packet come late, a duplicate (a frame's last packet sent twice) and a retransmission
    # of an older one name nothing, and the newest stays the newest.
    assert gaps.on_packet(SSRC, 12) == []
    assert gaps.on_packet(SSRC, 14) == []
    assert gaps.on_packet(SSRC, 15) == []
    # Across the wrap.
    gaps = GapWatch()
    gaps.on_packet(SSRC, 65534)
    assert gaps.on_packet(SSRC, 1) == [65535, 0]
    # A silence (more than one NACK entry's worth) is left to the silence watch.
    assert gaps.on_packet(SSRC, 2 + NACK_GAP_MAX + 1) == []
    assert gaps.on_packet(SSRC, 2 + NACK_GAP_MAX + 3) == [2 + NACK_GAP_MAX + 2]
    # A new sender (rebuilt: a new SSRC) starts afresh.
    assert gaps.on_packet(SSRC + 1, 500) == []
    assert gaps.on_packet(SSRC + 1, 502) == [501]


def _counters(link: object) -> RepairCounters:
    receiver = getattr(link, "receiver")  # noqa: B009 (VideoLink is generic)
    assert receiver.repairs is not None
    counters: RepairCounters = receiver.repairs.counters()
    return counters


async def test_on_a_clean_link_each_missing_packet_is_asked_for_once_at_once() -> None:
    # One packet in ~40 lost: under the 3 % that makes a link lossy.
    async with video_link(lambda to: DropEvery(to, every=30), NackLog, pattern="smpte") as link:
        media, back = link.media, link.feedback
        assert back is not None
        await wait_until(lambda: len(media.gap_seen) >= 13, timeout=30)
        await wait_until(lambda: _counters(link).repaired >= 13, timeout=10)
        counters = _counters(link)
        with media._lock, back._lock:
            # (The stream's first gap may come before the jitter buffer times its packets,
            # and its retransmission then waits for a retry.)
            asked = {seq: list(back.asked.get(seq, [])) for seq in list(media.gap_seen)[1:]}
        # Asked by the receiver itself as the gap arrived, and repaired by that one NACK (the
        # sender took it), the jitter buffer's own first ask dropped as a repeat. (A machine
        # loaded enough to drop packets at the socket can make the link lossy for a while.)
        assert counters.asked_at_once >= 13, counters
        assert counters.asks_copied <= 0.2 * counters.asked_at_once, counters
        once = [seq for seq, times in asked.items() if len(times) == 1]
        assert len(once) >= 0.8 * len(asked), asked


class _FirstNackLost(NackLog):
    """Loses every NACK that asks for a packet for the first time (the receiver's own, sent
    at once): only a copy can bring the repair."""

    def lost(self, data: bytes) -> bool:
        with self._lock:
            first = any(seq not in self.asked for seq in nacked(data))
        super().lost(data)
        return first


async def test_on_a_lossy_link_the_jitter_buffers_first_ask_goes_too_as_a_copy() -> None:
    # One packet in ~10 lost: a lossy link, where a lost NACK cost its frame a second try.
    async with video_link(
        lambda to: DropEvery(to, every=8),
        _FirstNackLost,
        pattern="smpte",
        motion=4,
        bitrate_kbps=4000,
    ) as link:
        media, repairs = link.media, link.receiver.repairs
        assert repairs is not None
        # Judged lossy over its first second (asked before that: no copy).
        await wait_until(lambda: repairs.lossy.on, timeout=10)
        lossy_from, before = time.monotonic(), _counters(link)

        def repairs_ms() -> list[float]:
            with media._lock:
                return [
                    (media.retransmitted[seq] - seen) * 1000
                    for seq, seen in media.gap_seen.items()
                    if seq in media.retransmitted and seen > lossy_from
                ]

        def enough() -> bool:
            counters = _counters(link)
            return (
                counters.asks_copied >= before.asks_copied + 20
                and counters.repaired >= before.repaired + 20
                and len(repairs_ms()) >= 20
            )

        await wait_until(enough, timeout=30)
        counters = _counters(link)
        assert repairs.lossy.on
        copied = counters.asks_copied - before.asks_copied
        assert copied >= 0.7 * (counters.asked_at_once - before.asked_at_once), counters
        # The copies brought the repairs the lost NACKs could not, a round trip after the
        # gap (~2 ms here): not at the jitter buffer's retry, RTX_RETRY_MIN_MS (33 ms) on.
        times = repairs_ms()
        assert statistics.median(times) < RTX_RETRY_MIN_MS / 2, sorted(times)
