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

    def __post_init__(self) -> None:
        for name in ("loss", "reorder", "duplicate"):
            value = getattr(self, name)
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name}: must be within 0-1, not {value}")
        for name in ("delay", "jitter"):
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
