"""A lost packet is asked for as soon as its gap shows: the repair's wait is the link's round
trip, not the RTCP schedule's."""

from __future__ import annotations

import statistics

from conftest import wait_until
from support.rtcp import DropEvery, NackLog
from support.video_link import video_link


async def test_a_missing_packet_is_asked_for_as_soon_as_its_gap_shows() -> None:
    async with video_link(DropEvery, NackLog, pattern="smpte") as link:
        receiver, media, back = link.receiver, link.media, link.feedback
        assert back is not None
        await wait_until(lambda: len(back.asked) >= 40, timeout=30)
        with media._lock, back._lock:
            waits = [
                (back.asked[seq][0] - seen) * 1000
                for seq, seen in media.gap_seen.items()
                if seq in back.asked
            ]
        assert len(waits) >= 30, waits
        # Each NACK left with the packet after the gap, give or take the threads' scheduling.
        # (Held to the RTCP schedule, AVPF's one early packet per interval, whose early slots
        # the transport-wide feedback also takes: 13 ms at the median, 23 at p90.)
        within = sum(wait < 10 for wait in waits) / len(waits)
        assert within >= 0.75, (statistics.median(waits), sorted(waits))
        # And each was repaired.
        assert receiver.repairs is not None
        assert receiver.repairs.counters().lost == 0
