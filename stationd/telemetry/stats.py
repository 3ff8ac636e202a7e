"""Link statistics of one telemetry stream: loss over a sliding window and silence. Pure."""

from __future__ import annotations

import collections


class LinkStats:
    """Loss over the last ``window`` sequence numbers, and silence since the last datagram."""

    def __init__(self, window: int) -> None:
        self.window = max(1, window)
        self.received = 0
        self.first_seq: int | None = None
        self.last_seq: int | None = None
        self.last_at: float | None = None
        self.started_at: float | None = None
        self._recent: collections.deque[int] = collections.deque()

    def start(self, now: float) -> None:
        """The stream was requested at ``now``: silence counts from here until data arrives."""
        self.started_at = now

    def accepted(self, seq: int, now: float) -> None:
        if self.first_seq is None or (
            self.last_seq is not None and seq - self.last_seq > self.window
        ):
            # First datagram, or the platform restarted its stream further on: start over.
            self.first_seq = seq
            self._recent.clear()
        self.received += 1
        self.last_seq = seq
        self.last_at = now
        self._recent.append(seq)
        while self._recent and self._recent[0] <= seq - self.window:
            self._recent.popleft()

    @property
    def loss_pct(self) -> float:
        """Share of the expected sequence numbers in the window that never arrived."""
        if self.last_seq is None or self.first_seq is None:
            return 0.0
        expected = min(self.window, self.last_seq - self.first_seq + 1)
        return round(100.0 * max(0, expected - len(self._recent)) / expected, 1)

    def silence(self, now: float) -> float | None:
        """Seconds without a valid datagram (since the request when none came yet)."""
        since = self.last_at if self.last_at is not None else self.started_at
        return None if since is None else max(0.0, now - since)
