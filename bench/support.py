"""Shared bench helpers: percentiles, free ports, a platform process and its resource use."""

from __future__ import annotations

import asyncio
import os
import socket
import statistics
import sys
import time
from pathlib import Path
from typing import BinaryIO

from brasidas import security
from brasidas.codecs.jsonrpc import Dispatcher, RpcError
from stationd.client import PlatformConnection

PLATFORM_LOG = Path(__file__).resolve().parent / "results" / "platform.log"


def percentiles(samples_ms: list[float]) -> dict[str, float]:
    ordered = sorted(samples_ms)

    def at(q: float) -> float:
        return round(ordered[min(len(ordered) - 1, int(q * len(ordered)))], 3)

    return {"p50": at(0.50), "p99": at(0.99), "mean": round(statistics.fmean(ordered), 3)}


def free_port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


async def start_platform(*overrides: str, sim: bool = True) -> asyncio.subprocess.Process:
    """``brasidas-platform --sim`` as a child process, with every port free."""
    args = [sys.executable, "-m", "platformd"]
    if sim:
        args.append("--sim")
    defaults = [
        f"signaling.port={free_port()}",
        f"beacon.port={free_port(socket.SOCK_DGRAM)}",
        f"velocity.port={free_port(socket.SOCK_DGRAM)}",
    ]
    for item in [*defaults, *overrides]:
        args += ["--set", item]
    # Its log goes to a file: a pipe nobody reads would fill and block the platform's loop.
    with _platform_log() as log:
        return await asyncio.create_subprocess_exec(
            *args, stdout=asyncio.subprocess.DEVNULL, stderr=log
        )


def _platform_log() -> BinaryIO:
    """bench/results/platform.log, appended to by every platform a bench starts."""
    PLATFORM_LOG.parent.mkdir(exist_ok=True)
    return PLATFORM_LOG.open("ab")


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return round(int(line.split()[1]) / 1024, 1)
    raise RuntimeError("no VmRSS")


def cpu_seconds(pid: int) -> float:
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


async def wait_ready(port: int, timeout: float = 15.0) -> None:
    """Until something accepts TCP connections on 127.0.0.1:``port``."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            _, writer = await asyncio.open_connection("127.0.0.1", port)
            writer.close()
            await writer.wait_closed()
            return
        except OSError:
            await asyncio.sleep(0.05)
    raise TimeoutError(f"platform did not start: nothing on port {port}")


async def connect_to_platform(port: int, platform_id: str = "brasidas-1") -> PlatformConnection:
    """Wait for a platform process's signaling port, then open a session as a station would."""
    await wait_ready(port)
    connection = PlatformConnection(
        platform_id,
        f"http://127.0.0.1:{port}",
        station_id="bench",
        fleet_key=security.load_key(security.default_key_path()),
    )
    await connection.open()
    return connection


async def stop_process(process: asyncio.subprocess.Process, timeout: float = 10.0) -> None:
    """SIGTERM, then SIGKILL if it is still there after ``timeout``."""
    if process.returncode is not None:
        return
    process.terminate()
    try:
        await asyncio.wait_for(process.wait(), timeout)
    except TimeoutError:
        process.kill()
        await process.wait()


async def station_connect(api: Dispatcher, url: str, timeout: float = 20.0) -> None:
    """Have a station daemon (its local ``api``) connect to the platform ``brasidas-1``."""
    deadline = time.monotonic() + timeout
    while True:
        try:
            await api.call_local("connect", platform_id="brasidas-1", url=url)
            return
        except RpcError:
            if time.monotonic() > deadline:
                raise
            await asyncio.sleep(0.1)
