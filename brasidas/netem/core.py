"""The link emulator's impairment schedule, sans-IO: frames in with the time, frames out when due.

:class:`Impairment` is one direction of a link. :meth:`Impairment.feed` takes a frame and the
current time and decides, from a seeded random source, whether it is lost, duplicated, sent
ahead of the queue (reordered) or delayed by ``delay ± jitter``; :meth:`Impairment.due`
returns the frames whose time has come, in delivery order, and :meth:`Impairment.deadline`
says when the next one is. A cut link drops everything (and what was in flight) until
restored. The same seed and the same input times give the same decisions, so a failing run
can be replayed.
"""

from __future__ import annotations

import heapq
import random
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Profile:
    """What one direction of a link does to frames. Probabilities are 0-1, times seconds."""

    loss: float = 0.0
    delay: float = 0.0
    jitter: float = 0.0
    """Uniform in ``delay ± jitter`` (never below zero): frames overtake each other."""
    reorder: float = 0.0
    """Share of frames sent at once, ahead of the ones being delayed (as netem's reorder)."""
    duplicate: float = 0.0
    rate_kbps: float = 0.0
    """Capacity (token bucket, kbit/s; 0: unlimited): frames wait for tokens in a queue of
    at most ``queue_s`` of waiting, and are dropped beyond it (a radio link's capacity drop)."""
    burst_bytes: int = 3000
    """The bucket's depth: what may leave at once after the link was idle."""
    queue_s: float = 0.1

    def __post_init__(self) -> None:
        for name in ("loss", "reorder", "duplicate"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name}: must be within 0-1, not {value}")
        for name in ("delay", "jitter", "rate_kbps", "burst_bytes", "queue_s"):
            if getattr(self, name) < 0:
                raise ValueError(f"{name}: must be >= 0")

    def describe(self) -> str:
        parts = [f"loss {self.loss:.0%}"]
        if self.delay or self.jitter:
            parts.append(f"delay {self.delay * 1000:.0f} ± {self.jitter * 1000:.0f} ms")
        if self.reorder:
            parts.append(f"reorder {self.reorder:.0%}")
        if self.duplicate:
            parts.append(f"duplicate {self.duplicate:.0%}")
        if self.rate_kbps:
            parts.append(f"rate {self.rate_kbps:g} kbit/s")
        return ", ".join(parts)


CLEAN = Profile()


@dataclass
class Counters:
    received: int = 0
    delivered: int = 0
    lost: int = 0
    duplicated: int = 0
    reordered: int = 0
    cut: int = 0
    """Dropped because the link was cut (on arrival or in flight)."""
    overflow: int = 0
    """Dropped because the rate limit's queue was full."""


@dataclass(order=True)
class _Pending:
    when: float
    order: int
    frame: bytes = field(compare=False)


class Impairment:
    """One direction of an emulated link."""

    def __init__(self, profile: Profile = CLEAN, *, seed: int = 0) -> None:
        self.profile = profile
        self.seed = seed
        self.random = random.Random(seed)
        self.counters = Counters()
        self.is_cut = False
        self._queue: list[_Pending] = []
        self._order = 0
        self._tokens = 0.0
        """Bytes the bucket holds (negative: owed by frames waiting in its queue)."""
        self._tokens_at: float | None = None

    def set_profile(self, profile: Profile) -> None:
        """New impairments apply to frames fed from now on."""
        self.profile = profile

    def cut(self) -> None:
        """Drop every frame, those in flight included, until :meth:`restore`."""
        self.is_cut = True
        self.counters.cut += len(self._queue)
        self._queue.clear()

    def restore(self) -> None:
        self.is_cut = False

    def feed(self, frame: bytes, now: float) -> None:
        """One frame entering the link at ``now``."""
        self.counters.received += 1
        if self.is_cut:
            self.counters.cut += 1
            return
        profile, rng = self.profile, self.random
        # Draw every number every time, so one setting changing does not shift the others.
        lost = rng.random() < profile.loss
        duplicate = rng.random() < profile.duplicate
        ahead = rng.random() < profile.reorder
        delays = (rng.uniform(-1.0, 1.0), rng.uniform(-1.0, 1.0))
        if lost:
            self.counters.lost += 1
            return
        wait = self._rate_wait(len(frame), now)
        if wait is None:
            self.counters.overflow += 1
            return
        now += wait
        copies = 2 if duplicate else 1
        self.counters.duplicated += copies - 1
        for copy in range(copies):
            if ahead and copy == 0:
                self.counters.reordered += 1
                when = now
            else:
                when = now + max(0.0, profile.delay + profile.jitter * delays[copy])
            self._order += 1
            heapq.heappush(self._queue, _Pending(when, self._order, frame))

    def _rate_wait(self, size: int, now: float) -> float | None:
        """How long a frame of ``size`` bytes waits for tokens; None: the queue is full."""
        profile = self.profile
        if not profile.rate_kbps:
            return 0.0
        bytes_per_s = profile.rate_kbps * 125
        if self._tokens_at is None:
            self._tokens = float(profile.burst_bytes)
        else:
            refill = (now - self._tokens_at) * bytes_per_s
            self._tokens = min(float(profile.burst_bytes), self._tokens + refill)
        self._tokens_at = now
        wait = max(0.0, size - self._tokens) / bytes_per_s
        if wait > profile.queue_s:
            return None
        self._tokens -= size
        return wait

    def deadline(self) -> float | None:
        """When the next frame is due, or None when nothing is in flight."""
        return self._queue[0].when if self._queue else None

    def due(self, now: float) -> list[bytes]:
        """The frames to deliver at ``now``, in order."""
        out: list[bytes] = []
        while self._queue and self._queue[0].when <= now:
            out.append(heapq.heappop(self._queue).frame)
        self.counters.delivered += len(out)
        return out

    @property
    def in_flight(self) -> int:
        return len(self._queue)
