"""Issue 19, defect 2: idle connections from a stranger must not exhaust the platform's file
descriptors. The platform runs as a process under a lowered open-file limit (256, so what took
1,100 connections at systemd's 1,024 takes a few hundred); the attacker holds idle connections
from its own loopback address, the station connects from 127.0.0.1."""

from __future__ import annotations

import asyncio
import os
import resource
import signal
import socket
from pathlib import Path

from support.processes import sim_platform, wait_for_signaling

from brasidas import security
from stationd.client import PlatformConnection

FD_LIMIT = 256
IDLE_CONNECTIONS = 600


def _lower_fd_limit() -> None:
    resource.setrlimit(resource.RLIMIT_NOFILE, (FD_LIMIT, FD_LIMIT))


def _open_idle(port: int, count: int) -> list[socket.socket]:
    """``count`` connections from 127.0.0.2 that never send a byte (non-blocking: a
    connection the platform does not accept waits in its backlog)."""
    idle = []
    for _ in range(count):
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setblocking(False)
        sock.bind(("127.0.0.2", 0))
        sock.connect_ex(("127.0.0.1", port))
        idle.append(sock)
    return idle


async def test_idle_connections_leave_the_station_a_way_in(tmp_path: Path) -> None:
    log_path = tmp_path / "platform.log"
    with log_path.open("wb") as log:
        process, port = await sim_platform(stderr=log, preexec_fn=_lower_fd_limit)
    idle: list[socket.socket] = []
    try:
        await wait_for_signaling(port, process)
        idle = _open_idle(port, IDLE_CONNECTIONS)
        await asyncio.sleep(1.0)  # the platform takes them in (or fails to)
        connection = PlatformConnection(
            "brasidas-1",
            f"http://127.0.0.1:{port}",
            station_id="station-under-attack",
            fleet_key=security.load_key(security.default_key_path()),
            timeout=10,
        )
        await asyncio.wait_for(connection.open(), 20)  # "cannot connect" before the fix
        try:
            assert (await connection.call("heartbeat"))["manual_override"] is False
            # A pipeline needs descriptors of its own (GStreamer's poll): before the fix,
            # starting one out of them killed the daemon (a trap in libglib).
            started = await connection.call("start_stream", name="audio_out")
            assert started["name"] == "audio_out", started
            await connection.call("stop_stream", name="audio_out")
        finally:
            await connection.close()
        assert process.returncode is None
        descriptors = len(await asyncio.to_thread(os.listdir, f"/proc/{process.pid}/fd"))
        assert descriptors < FD_LIMIT - 64, f"{descriptors} descriptors open"
        log_text = await asyncio.to_thread(log_path.read_text, errors="replace")
        assert log_text.count("out of system resource") == 0
        assert log_text.count("\n") < 500, f"{log_text.count(chr(10))} log lines"
        process.send_signal(signal.SIGTERM)
        assert await asyncio.wait_for(process.wait(), 10) == 0
    finally:
        for sock in idle:
            sock.close()
        if process.returncode is None:
            process.kill()
            await process.wait()
