"""The platform daemon as a process, as systemd runs it: start, serve, stop on SIGTERM."""

from __future__ import annotations

import asyncio
import signal
import socket
import sys
from pathlib import Path

from conftest import free_tcp_port, free_udp_port

from brasidas import security
from brasidas.rpc import RpcClient


async def _wait_for_signaling(port: int, process: asyncio.subprocess.Process) -> None:
    async def poll() -> None:
        while True:
            assert process.returncode is None, "platform exited during start"
            try:
                with socket.create_connection(("127.0.0.1", port), timeout=0.2):
                    return
            except OSError:
                await asyncio.sleep(0.05)

    await asyncio.wait_for(poll(), 15)


async def test_sim_platform_creates_key_serves_and_stops_cleanly_on_sigterm() -> None:
    port = free_tcp_port()
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "platformd",
        "--sim",
        "--set",
        f"signaling.port={port}",
        "--set",
        f"beacon.port={free_udp_port()}",
        "--set",
        f"velocity.port={free_udp_port()}",
        stderr=asyncio.subprocess.PIPE,
    )
    try:
        await _wait_for_signaling(port, process)
        assert security.default_key_path().exists()  # --sim made one in the state dir
        async with RpcClient(f"http://127.0.0.1:{port}/rpc/ws") as client:
            assert (await client.call("challenge"))["auth"] == "hmac-sha256"
        # The entry point keeps Python's ssl module (and OpenSSL's libssl) out: ~4 MB of RSS.
        maps = await asyncio.to_thread(Path(f"/proc/{process.pid}/maps").read_text)
        assert "libssl" not in maps and "_ssl." not in maps
        process.send_signal(signal.SIGTERM)
        assert await asyncio.wait_for(process.wait(), 10) == 0
        assert process.stderr is not None
        log = (await process.stderr.read()).decode()
        assert "platform stopped" in log
        assert "Traceback" not in log
    finally:
        if process.returncode is None:
            process.kill()
            await process.wait()


async def test_port_in_use_is_a_clear_error() -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        process = await asyncio.create_subprocess_exec(
            sys.executable,
            "-m",
            "platformd",
            "--sim",
            "--insecure",
            "--set",
            f"signaling.port={port}",
            "--set",
            "beacon.enabled=false",
            "--set",
            f"velocity.port={free_udp_port()}",
            stderr=asyncio.subprocess.PIPE,
        )
        _, err = await asyncio.wait_for(process.communicate(), 15)
    assert process.returncode == 1
    assert "address already in use" in err.decode().lower()
