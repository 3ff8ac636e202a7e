"""Capped exponential backoff with jitter: the one retry schedule of every reconnect loop."""

from __future__ import annotations

import random
from collections.abc import Callable


class Backoff:
    """Delays ``initial``, ``initial * factor``, ... capped at ``maximum``, each shortened by up
    to ``jitter`` (a fraction) at random so that retries started together spread out.

    ``next()`` gives the delay before the next attempt; ``reset()`` after a success starts
    the schedule over. ``random`` (a source in [0, 1)) is injectable for tests.
    """

    def __init__(
        self,
        initial: float,
        maximum: float,
        *,
        factor: float = 2.0,
        jitter: float = 0.1,
        random: Callable[[], float] = random.random,
    ) -> None:
        if initial <= 0 or maximum < initial:
            raise ValueError(f"backoff needs 0 < initial <= maximum, got {initial}, {maximum}")
        if factor < 1.0:
            raise ValueError(f"backoff factor must be >= 1, got {factor}")
        if not 0.0 <= jitter < 1.0:
            raise ValueError(f"backoff jitter must be in [0, 1), got {jitter}")
        self.initial = initial
        self.maximum = maximum
        self.factor = factor
        self.jitter = jitter
        self._random = random
        self._base = initial
        self.attempts = 0
        """Delays handed out since the last reset."""

    def next(self) -> float:
        """The delay before the next attempt (the schedule then grows)."""
        base = self._base
        self._base = min(base * self.factor, self.maximum)
        self.attempts += 1
        return base * (1.0 - self.jitter * self._random())

    def reset(self) -> None:
        """A success: the next delay is ``initial`` again."""
        self._base = self.initial
        self.attempts = 0
