"""Platform daemons run as child processes."""

from __future__ import annotations

import asyncio
import socket
import sys
from typing import Any

from conftest import free_tcp_port, free_udp_port


async def sim_platform(
    *settings: str, port: int | None = None, **popen: Any
) -> tuple[asyncio.subprocess.Process, int]:
    """``python -m platformd --sim`` with signaling on ``port`` (a free one by default), the
    beacon and velocity on free ports, then ``settings`` (``SECTION.KEY=VALUE``, later ones
    win); ``popen``: create_subprocess_exec's keywords (``stderr``, ``preexec_fn``). The
    process, started (:func:`wait_for_signaling` waits until it serves), and its port."""
    port = free_tcp_port() if port is None else port
    ports = (
        f"signaling.port={port}",
        f"beacon.port={free_udp_port()}",
        f"velocity.port={free_udp_port()}",
    )
    args = [arg for setting in (*ports, *settings) for arg in ("--set", setting)]
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "platformd", "--sim", *args, **popen
    )
    return process, port


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
