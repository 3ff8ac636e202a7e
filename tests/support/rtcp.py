"""RTCP feedback as the tests read it on the wire."""

from __future__ import annotations

import threading
import time

from lossy_udp import LossyRelay

RTCP_RTPFB = 205
NACK_FMT = 1


def nacked(rtcp: bytes) -> list[int]:
    """The sequence numbers a (compound or reduced-size) RTCP packet asks for (RFC 4585)."""
    asked: list[int] = []
    offset = 0
    while offset + 4 <= len(rtcp):
        length = (int.from_bytes(rtcp[offset + 2 : offset + 4], "big") + 1) * 4
        if rtcp[offset + 1] == RTCP_RTPFB and rtcp[offset] & 0x1F == NACK_FMT:
            fci = rtcp[offset + 12 : offset + length]
            for at in range(0, len(fci) - 3, 4):
                pid = int.from_bytes(fci[at : at + 2], "big")
                mask = int.from_bytes(fci[at + 2 : at + 4], "big")
                asked.append(pid)
                asked += [(pid + bit + 1) & 0xFFFF for bit in range(16) if mask >> bit & 1]
        offset += length
    return asked


class NackLog(LossyRelay):
    """Passes the receiver's RTCP on, noting when each sequence number was asked for (NACK)."""

    def __init__(self, to: tuple[str, int]) -> None:
        self._lock = threading.Lock()  # before the relay's thread starts
        self.asked: dict[int, list[float]] = {}
        """Sequence number → the times it was asked for, in order."""
        super().__init__(to, loss=0.0)

    def lost(self, data: bytes) -> bool:
        now = time.monotonic()
        with self._lock:
            for seq in nacked(data):
                self.asked.setdefault(seq, []).append(now)
        return False
