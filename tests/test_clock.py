"""The injectable clock: timers in order at their own time, cancel, sleep and timeouts."""

from __future__ import annotations

import asyncio

import pytest

from brasidas.clock import LoopClock, ManualClock, sleep, timeout_at


async def test_manual_clock_runs_due_timers_in_order_at_their_time() -> None:
    clock = ManualClock(start=10.0)
    fired: list[tuple[str, float]] = []
    clock.call_at(10.5, lambda: fired.append(("b", clock.time())))
    clock.call_at(10.2, lambda: fired.append(("a", clock.time())))
    cancelled = clock.call_at(10.3, lambda: fired.append(("never", clock.time())))
    cancelled.cancel()
    clock.call_at(12.0, lambda: fired.append(("later", clock.time())))
    clock.advance(1.0)
    assert fired == [("a", 10.2), ("b", 10.5)]
    assert clock.time() == 11.0
    clock.call_at(5.0, lambda: fired.append(("past", clock.time())))  # due: soon, not inline
    assert fired[-1][0] == "b"
    await asyncio.sleep(0)
    assert fired[-1] == ("past", 11.0)


async def test_sleep_and_timeout_follow_the_manual_clock() -> None:
    clock = ManualClock()
    sleeper = asyncio.create_task(sleep(clock, 2.0))
    await asyncio.sleep(0.01)
    clock.advance(1.9)
    await asyncio.sleep(0.01)
    assert not sleeper.done()
    clock.advance(0.1)
    await asyncio.wait_for(sleeper, 1.0)

    async def waits_forever() -> None:
        async with timeout_at(clock, clock.time() + 0.5):
            await asyncio.Event().wait()

    waiter = asyncio.create_task(waits_forever())
    await asyncio.sleep(0.01)
    clock.advance(0.5)
    with pytest.raises(TimeoutError):
        await asyncio.wait_for(waiter, 1.0)


async def test_loop_clock_is_the_loops_time() -> None:
    clock = LoopClock()
    started = clock.time()
    await sleep(clock, 0.02)
    assert clock.time() - started >= 0.02
    async with timeout_at(clock, None):
        await asyncio.sleep(0)
