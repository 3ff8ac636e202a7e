"""The suite's leak check fails a test that leaves a timer, a task, a thread or a busy
executor worker behind, and lets pass one whose thread finishes within the grace or whose
pool worker is idle."""

from __future__ import annotations

import shutil
from pathlib import Path

import pytest

CASES = """
import asyncio
import threading
import time
from concurrent.futures import ThreadPoolExecutor

RELEASE = threading.Event()


async def test_left_timer() -> None:
    asyncio.get_running_loop().call_later(30, print)


async def test_left_task() -> None:
    asyncio.get_running_loop().create_task(asyncio.sleep(30), name="sleeper")


async def test_left_thread() -> None:
    threading.Thread(target=RELEASE.wait, name="waiter", daemon=True).start()


async def test_left_busy_worker() -> None:
    pool = ThreadPoolExecutor(thread_name_prefix="busy")
    pool.submit(RELEASE.wait)
    pool.shutdown(wait=False)


def test_left_thread_from_a_plain_test() -> None:
    threading.Thread(target=RELEASE.wait, name="waiter", daemon=True).start()


async def test_thread_that_finishes_soon_passes() -> None:
    threading.Thread(target=time.sleep, args=(0.1,), daemon=True).start()


async def test_idle_pool_worker_passes() -> None:
    await asyncio.to_thread(time.sleep, 0.01)


async def test_cancelled_timer_passes() -> None:
    asyncio.get_running_loop().call_later(30, print).cancel()


def test_zz_release_the_waiters() -> None:
    RELEASE.set()
"""


def test_the_leak_check_fails_what_is_left_behind(pytester: pytest.Pytester) -> None:
    conftest = (Path(__file__).parent / "conftest.py").read_text()
    assert "THREAD_GRACE = 2.0" in conftest
    pytester.makeconftest(conftest.replace("THREAD_GRACE = 2.0", "THREAD_GRACE = 0.5"))
    shutil.copytree(Path(__file__).parent / "support", pytester.path / "support")  # its helpers
    pytester.makepyfile(test_cases=CASES)
    result = pytester.runpytest_subprocess(
        "-p", "no:cacheprovider", "-q", "-o", "asyncio_mode=auto"
    )
    result.assert_outcomes(passed=9, errors=5)
    result.stdout.fnmatch_lines(
        [
            "E*test left timers scheduled*print()*",
            "E*test left tasks running*sleeper*",
            "E*test left threads working*waiter*",
            "E*test left threads working*busy_*",
            "E*test left threads working*waiter*",
        ],
        consecutive=False,
    )
