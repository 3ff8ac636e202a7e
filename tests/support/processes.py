"""Platform daemons run as child processes."""

from __future__ import annotations

import asyncio
import socket


async def wait_for_signaling(port: int, process: asyncio.subprocess.Process) -> None:
    async def poll() -> None:
        while True:
            assert process.returncode is None, "platform exited during start"
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                    return
            except OSError:
                await asyncio.sleep(0.05)

    await asyncio.wait_for(poll(), 15)
