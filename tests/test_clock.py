"""The injectable clock: timers in order at their own time, cancel, sleep and timeouts; a
timeout that does not count a blocked loop's time."""

from __future__ import annotations

import asyncio

import pytest

from brasidas.clock import (
    LoopClock,
    ManualClock,
    RunningBudget,
    running_timeout,
    sleep,
    timeout_at,
)


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


async def test_a_running_timeout_does_not_count_a_stalled_loop() -> None:
    """0.3 s with checks every 0.05 s: a loop blocked for 1 s costs one check; a loop that
    keeps up times out at 0.3 s exactly; ``most`` bounds it in real time all the same."""
    clock = ManualClock()

    async def waits_forever(seconds: float = 0.3, most: float = 1.5) -> None:
        async with running_timeout(clock, seconds, step=0.05, most=most):
            await asyncio.Event().wait()

    waiter = asyncio.create_task(waits_forever())
    await asyncio.sleep(0.01)
    clock.advance(0.02)
    clock.stall(1.0)  # blocked: nothing ran, what fell due runs late
    clock.advance(0.0)
    await asyncio.sleep(0.01)
    assert not waiter.done(), "the stall was charged as silence"
    clock.advance(0.2)  # 0.05 (the stall) + 0.2 of running time: 0.05 left
    await asyncio.sleep(0.01)
    assert not waiter.done(), "timed out before 0.3 s of running time"
    clock.advance(0.05)
    with pytest.raises(TimeoutError):
        await asyncio.wait_for(waiter, 1.0)

    # Stalled again and again: given up at ``most`` all the same.
    waiter = asyncio.create_task(waits_forever(most=1.0))
    await asyncio.sleep(0.01)
    for _ in range(3):
        clock.stall(0.4)
        clock.advance(0.0)
        await asyncio.sleep(0)
    with pytest.raises(TimeoutError):
        await asyncio.wait_for(waiter, 1.0)


def test_running_budget_charges_a_late_check_as_one_step() -> None:
    budget = RunningBudget(0.3, step=0.05, most=1.5, now=100.0)
    assert budget.next_check() == pytest.approx(100.05)
    assert not budget.spent(100.051)  # on time (1 ms late): charged in full, up to a step
    assert not budget.spent(101.0)  # ~0.95 s late: the loop was blocked, one step charged
    assert budget.left == pytest.approx(0.2)
    for now in (101.05, 101.1, 101.15):
        assert not budget.spent(now)
    assert budget.spent(101.2)
    late = RunningBudget(0.3, step=0.05, most=1.5, now=100.0)
    assert late.spent(101.5)  # ``most`` after the start, whatever was charged
