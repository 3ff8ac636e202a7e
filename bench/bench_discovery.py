"""Discovery: start of ``brasidas-platform --sim`` to its first beacon heard, and beacon size.

Each run spawns the platform as a process (as an operator would) and listens on its beacon
port exactly as the station's discovery does (``stationd.discovery``: same socket options,
same authentication), timing from just before the spawn to the first beacon accepted.
"""

from __future__ import annotations

import asyncio
import signal
import socket
import time
from typing import Any

from bench.support import free_port, percentiles, start_platform
from brasidas import security
from brasidas.discovery import PlatformDirectory, listen_socket

RUNS = 5


class _Listener(asyncio.DatagramProtocol):
    def __init__(self, directory: PlatformDirectory) -> None:
        self.directory = directory
        self.heard = asyncio.Event()
        self.sizes: list[int] = []

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        if self.directory.receive(data, addr[0]) is not None:
            self.sizes.append(len(data))
            self.heard.set()


async def _first_beacon(key: bytes) -> tuple[float, list[int]]:
    port = free_port(socket.SOCK_DGRAM)
    loop = asyncio.get_running_loop()
    directory = PlatformDirectory(key, 4.0)
    transport, listener = await loop.create_datagram_endpoint(
        lambda: _Listener(directory), sock=listen_socket("0.0.0.0", port)
    )
    started = time.perf_counter()
    process = await start_platform(f"beacon.port={port}")
    try:
        await asyncio.wait_for(listener.heard.wait(), 15)
        elapsed = time.perf_counter() - started
        await asyncio.sleep(0.1)
        return elapsed, listener.sizes
    finally:
        transport.close()
        process.send_signal(signal.SIGTERM)
        await process.wait()


async def run() -> dict[str, Any]:
    key = security.load_or_create_key(security.default_key_path())
    await _first_beacon(key)  # warm the page cache: the operator's second start, not the first
    times_ms: list[float] = []
    sizes: list[int] = []
    for _ in range(RUNS):
        elapsed, heard = await _first_beacon(key)
        times_ms.append(elapsed * 1000)
        sizes.extend(heard)
    figures: dict[str, Any] = {
        f"start_to_first_beacon_ms_{name}": value for name, value in percentiles(times_ms).items()
    }
    figures["start_to_first_beacon_ms_max"] = round(max(times_ms), 1)
    figures["start_to_first_beacon_target_ms"] = 1500
    figures["beacon_bytes"] = max(sizes)
    figures["beacon_bytes_limit"] = 100
    return figures
