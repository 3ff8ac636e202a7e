"""A lost packet is asked for as soon as its gap shows: the repair's wait is the link's round
trip, not the RTCP schedule's."""

from __future__ import annotations

import statistics
import threading
import time

from conftest import wait_until
from lossy_udp import LossyRelay
from support.rtcp import NackLog
from support.video_link import video_link

from brasidas.media.video import PAYLOAD_TYPE


class _DropSome(LossyRelay):
    """Loses the first copy of every 15th media packet that is not a frame's last (so the
    gap shows at once, at the next packet of the same frame); notes when each gap showed."""

    def __init__(self, to: tuple[str, int]) -> None:
        self._lock = threading.Lock()  # before the relay's thread starts
        self.missing: set[int] = set()
        self.gap_seen: dict[int, float] = {}
        self._count = 0
        super().__init__(to, loss=0.0)

    def lost(self, data: bytes) -> bool:
        if len(data) < 4 or data[1] & 0x7F != PAYLOAD_TYPE:
            return False
        seq = int.from_bytes(data[2:4], "big")
        with self._lock:
            for missing in self.missing:
                if missing not in self.gap_seen and (seq - missing) & 0xFFFF < 0x8000:
                    self.gap_seen[missing] = time.monotonic()
            if data[1] & 0x80 or seq in self.missing:
                return False
            self._count += 1
            if self._count % 15:
                return False
            self.missing.add(seq)
            return True


async def test_a_missing_packet_is_asked_for_as_soon_as_its_gap_shows() -> None:
    async with video_link(_DropSome, NackLog, pattern="smpte") as link:
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
