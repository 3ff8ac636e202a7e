"""An injectable clock for actors whose schedule is time-driven (refreshes, polls, retries).

:class:`LoopClock` is the event loop's monotonic clock; :class:`ManualClock` is one that moves
only when told (tests: ten seconds of schedule in a few milliseconds, the I/O still real).
:func:`running_timeout` is a timeout that does not count the time the loop was blocked.
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Protocol


class Cancellable(Protocol):
    def cancel(self) -> None: ...


class Clock(Protocol):
    def time(self) -> float:
        """Monotonic seconds."""

    def call_at(self, when: float, callback: Callable[[], None]) -> Cancellable:
        """Run ``callback`` on the loop once :meth:`time` reaches ``when``."""


class LoopClock:
    """The running event loop's clock (``loop.time()``, ``loop.call_at``)."""

    def time(self) -> float:
        return asyncio.get_running_loop().time()

    def call_at(self, when: float, callback: Callable[[], None]) -> Cancellable:
        return asyncio.get_running_loop().call_at(when, callback)


async def sleep(clock: Clock, delay: float) -> None:
    """Sleep ``delay`` seconds of ``clock``."""
    future: asyncio.Future[None] = asyncio.get_running_loop().create_future()

    def wake() -> None:
        if not future.done():
            future.set_result(None)

    handle = clock.call_at(clock.time() + delay, wake)
    try:
        await future
    finally:
        handle.cancel()


@asynccontextmanager
async def timeout_at(clock: Clock, when: float | None) -> AsyncIterator[None]:
    """Like ``asyncio.timeout_at`` but on ``clock``: TimeoutError once it reaches ``when``."""
    loop = asyncio.get_running_loop()
    async with asyncio.timeout(None) as scope:
        if when is None:
            yield
            return

        def expire() -> None:
            if not scope.expired():
                scope.reschedule(loop.time())

        handle = clock.call_at(when, expire)
        try:
            yield
        finally:
            handle.cancel()


@asynccontextmanager
async def running_timeout(
    clock: Clock, seconds: float, *, step: float, most: float
) -> AsyncIterator[None]:
    """TimeoutError once the event loop has been free to run for ``seconds``, or after ``most``.

    For waits on an answer that arrives through the loop (a serial line's reader, a simulator
    on the same loop): time the loop spent blocked by synchronous work elsewhere (an import,
    a slow callback, a starved CPU) is time nobody could read the answer in, and is not
    counted against it (:class:`RunningBudget`). On a loop that keeps up it is a plain timeout.
    """
    loop = asyncio.get_running_loop()
    budget = RunningBudget(seconds, step=step, most=most, now=clock.time())
    async with asyncio.timeout(None) as scope:
        handle: Cancellable | None = None

        def check() -> None:
            nonlocal handle
            if budget.spent(clock.time()):
                handle = None
                if not scope.expired():
                    scope.reschedule(loop.time())
            else:
                handle = clock.call_at(budget.next_check(), check)

        handle = clock.call_at(budget.next_check(), check)
        try:
            yield
        finally:
            if handle is not None:
                handle.cancel()


class RunningBudget:
    """Sans-IO: ``seconds`` of running time, checked every ``step`` (``now`` passed in).

    Each check charges the time since the previous one, but never more than ``step``: a check
    that comes late because the loop was blocked charges what an on-time one does. Real time
    still bounds it: the budget is spent ``most`` seconds after it began, whatever happened.
    """

    def __init__(self, seconds: float, *, step: float, most: float, now: float) -> None:
        self.left = seconds
        self.step = step
        self.deadline = now + max(most, seconds)
        self._last = now

    def next_check(self) -> float:
        """When the next check is due."""
        return min(self._last + min(self.step, self.left), self.deadline)

    def spent(self, now: float) -> bool:
        """Charge the time up to ``now`` (at most a step); True once nothing is left."""
        self.left -= min(max(0.0, now - self._last), self.step)
        self._last = now
        return self.left <= 1e-9 or now >= self.deadline - 1e-9


class _Timer:
    def __init__(self, callback: Callable[[], None]) -> None:
        self.callback: Callable[[], None] | None = callback

    def cancel(self) -> None:
        self.callback = None


class ManualClock:
    """A clock that moves only by :meth:`advance`; callbacks due run on the loop, in order."""

    def __init__(self, start: float = 1000.0) -> None:
        self._now = start
        self._timers: list[tuple[float, int, _Timer]] = []
        self._order = itertools.count()

    def time(self) -> float:
        return self._now

    def call_at(self, when: float, callback: Callable[[], None]) -> Cancellable:
        timer = _Timer(callback)
        if when <= self._now:  # already due: soon, never from inside the caller
            asyncio.get_running_loop().call_soon(self._fire, timer)
        else:
            heapq.heappush(self._timers, (when, next(self._order), timer))
        return timer

    def advance(self, seconds: float) -> None:
        """Move time on by ``seconds``, running what falls due at its own time."""
        target = self._now + seconds
        while self._timers and self._timers[0][0] <= target:
            when, _, timer = heapq.heappop(self._timers)
            self._now = max(self._now, when)
            self._fire(timer)
        self._now = target

    def stall(self, seconds: float) -> None:
        """Move time on by ``seconds`` as a blocked loop would: nothing runs meanwhile; what
        fell due runs late, at the next :meth:`advance`."""
        self._now += seconds

    @staticmethod
    def _fire(timer: _Timer) -> None:
        callback, timer.callback = timer.callback, None
        if callback is not None:
            callback()
