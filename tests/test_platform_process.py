"""The platform daemon as a process, as systemd runs it: start, serve, stop on SIGTERM."""

from __future__ import annotations

import asyncio
import signal
import socket
import sys
from pathlib import Path

from conftest import free_udp_port
from support.processes import sim_platform, wait_for_signaling

from brasidas import security
from brasidas.rpc import RpcClient
from platformd.sim.demo_area import demo_map
from stationd.client import PlatformConnection


async def test_sim_platform_creates_key_serves_and_stops_cleanly_on_sigterm() -> None:
    process, port = await sim_platform(stderr=asyncio.subprocess.PIPE)
    try:
        await wait_for_signaling(port, process)
        assert security.default_key_path().exists()  # --sim made one in the state dir
        async with RpcClient(f"http://127.0.0.1:{port}/rpc/ws") as client:
            assert (await client.call("challenge"))["auth"] == "hmac-sha256"
        # The entry point keeps Python's ssl module (and OpenSSL's libssl) out: ~4 MB of RSS.
        maps = await asyncio.to_thread(Path(f"/proc/{process.pid}/maps").read_text)
        assert "libssl" not in maps
        assert "_ssl." not in maps
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


HEAVY = ("numpy", "shapely", "libgeos", "openblas")
"""What an area map needs (~17 MB of RSS): mapped only once there is a map."""


async def test_a_platform_without_a_map_loads_no_shapely_until_one_is_loaded(
    tmp_path: Path,
) -> None:
    process, port = await sim_platform(
        "sim.demo_map=false",
        f"map.file={tmp_path / 'none' / 'map.geojson'}",
        stderr=asyncio.subprocess.DEVNULL,
    )
    maps = Path(f"/proc/{process.pid}/maps")
    try:
        await wait_for_signaling(port, process)
        connection = PlatformConnection(
            "brasidas-1",
            f"http://127.0.0.1:{port}",
            station_id="test",
            fleet_key=security.load_key(security.default_key_path()),
        )
        await connection.open()
        try:
            assert (await connection.call("get_map"))["map"] is None
            text = (await asyncio.to_thread(maps.read_text)).lower()
            assert [name for name in HEAVY if name in text] == []
            answer = await connection.call("load_map", map=demo_map(37.9415, 23.6530))
            assert answer["map"]["name"] == "demo field"
            assert (await connection.call("get_map"))["map"]["name"] == "demo field"
            text = (await asyncio.to_thread(maps.read_text)).lower()
            assert "shapely" in text
            assert "numpy" in text  # the test sees them when they are there
        finally:
            await connection.close()
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
