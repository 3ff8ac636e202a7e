"""The simulators' sending end of a serial line (platformd.sim.pty_line)."""

from __future__ import annotations

import asyncio
import os

from conftest import wait_until

from platformd.sim.pty_line import PtyLine


async def test_what_was_written_is_read_before_the_line_closes() -> None:
    """Closing the pty drops what its reader has not read yet: a replay ending while a busy
    driver was behind lost its last revolutions. ``drained`` waits for the reader."""
    line = PtyLine("test")
    fd = os.open(line.path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        line.write(b"x" * 1000)
        await wait_until(lambda: line.queued() == 1000)  # through the kernel's work queue

        async def read_late() -> bytes:
            await asyncio.sleep(0.3)  # the driver, slowed down
            return os.read(fd, 4096)

        reading = asyncio.create_task(read_late())
        await line.drained(timeout=5.0)
        assert reading.done()  # it waited for the read, not the timeout's whole 5 s
        line.close()
        assert await reading == b"x" * 1000
    finally:
        line.close()
        os.close(fd)


async def test_an_unread_line_closes_after_the_timeout() -> None:
    line = PtyLine("test")
    try:
        line.write(b"y" * 10)
        await wait_until(lambda: line.queued() == 10)
        loop = asyncio.get_running_loop()
        started = loop.time()
        await line.drained(timeout=0.2)  # nobody opened it: not waited for ever
        assert 0.2 <= loop.time() - started < 2.0
        assert line.queued() == 10
    finally:
        line.close()
