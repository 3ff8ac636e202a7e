"""RTCP feedback as the tests read it on the wire."""

from __future__ import annotations

import threading
import time

from lossy_udp import LossyRelay

from brasidas.media.reask import rtx_original_seq
from brasidas.media.repair import RTX_PAYLOAD_TYPE
from brasidas.media.video import PAYLOAD_TYPE

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


class DropEvery(LossyRelay):
    """Loses the first copy of every ``every``-th media packet that is not a frame's last (so
    the gap shows at once, at the next packet of the same frame); notes when each gap showed
    and when the lost packet's retransmission passed."""

    def __init__(self, to: tuple[str, int], every: int = 15) -> None:
        self._lock = threading.Lock()  # before the relay's thread starts
        self.every = every
        self.missing: set[int] = set()
        self.gap_seen: dict[int, float] = {}
        self.retransmitted: dict[int, float] = {}
        """Sequence number lost → when its first retransmission passed."""
        self._count = 0
        super().__init__(to, loss=0.0)

    def lost(self, data: bytes) -> bool:
        if len(data) >= 4 and data[1] & 0x7F == RTX_PAYLOAD_TYPE:
            original = rtx_original_seq(data)
            with self._lock:
                if original in self.missing:
                    self.retransmitted.setdefault(original, time.monotonic())
            return False
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
            if self._count % self.every:
                return False
            self.missing.add(seq)
            return True
