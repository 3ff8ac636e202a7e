"""Signaling round trip (WebSocket JSON-RPC vs a Pyro5 proxy), shutdown time, idle RSS."""

from __future__ import annotations

import asyncio
import signal
import sys
import time
from typing import Any

from bench.support import (
    connect_to_platform,
    free_port,
    percentiles,
    rss_mb,
    start_platform,
    wait_ready,
)

CALLS = 2000

PYRO_SERVER = """
import sys, Pyro5.api
@Pyro5.api.expose
class Target:
    def heartbeat(self):
        return {"ok": True}
daemon = Pyro5.api.Daemon(host="127.0.0.1", port=int(sys.argv[1]))
daemon.register(Target(), objectId="target")
print("ready", flush=True)
daemon.requestLoop()
"""


async def _brasidas_round_trips() -> tuple[list[float], dict[str, Any]]:
    port = free_port()
    process = await start_platform(f"signaling.port={port}")
    extra: dict[str, Any] = {}
    try:
        await wait_ready(port)
        await asyncio.sleep(1.0)  # let start-up settle before measuring idle memory
        extra["platform_rss_idle_mb"] = rss_mb(process.pid)
        connection = await connect_to_platform(port)
        samples = []
        try:
            for _ in range(100):  # warm-up
                await connection.call("heartbeat")
            for _ in range(CALLS):
                started = time.perf_counter()
                await connection.call("heartbeat")
                samples.append((time.perf_counter() - started) * 1000)
        finally:
            await connection.close()
        sent = time.perf_counter()
        process.send_signal(signal.SIGTERM)
        await asyncio.wait_for(process.wait(), 5)
        extra["platform_sigterm_exit_ms"] = round((time.perf_counter() - sent) * 1000, 1)
        extra["platform_sigterm_exit_status"] = process.returncode
        return samples, extra
    finally:
        if process.returncode is None:
            process.kill()
            await process.wait()


def _pyro_round_trips(port: int) -> list[float]:
    import Pyro5.api

    samples = []
    with Pyro5.api.Proxy(f"PYRO:target@127.0.0.1:{port}") as proxy:
        for _ in range(100):
            proxy.heartbeat()
        for _ in range(CALLS):
            started = time.perf_counter()
            proxy.heartbeat()
            samples.append((time.perf_counter() - started) * 1000)
    return samples


ECHO_SERVER = """
import asyncio, sys
from aiohttp import web
async def ws(request):
    socket = web.WebSocketResponse()
    await socket.prepare(request)
    async for message in socket:
        await socket.send_str(message.data)
    return socket
async def main():
    app = web.Application()
    app.router.add_get("/ws", ws)
    runner = web.AppRunner(app, access_log=None)
    await runner.setup()
    await web.TCPSite(runner, "127.0.0.1", int(sys.argv[1])).start()
    print("ready", flush=True)
    await asyncio.Event().wait()
asyncio.run(main())
"""


async def _aiohttp_echo_floor() -> list[float]:
    """Bare aiohttp WebSocket echo, no JSON-RPC: the transport's own floor on this machine."""
    import aiohttp

    port = free_port()
    server = await asyncio.create_subprocess_exec(
        sys.executable, "-c", ECHO_SERVER, str(port), stdout=asyncio.subprocess.PIPE
    )
    samples = []
    try:
        assert server.stdout is not None
        await asyncio.wait_for(server.stdout.readline(), 10)
        request = '{"jsonrpc":"2.0","id":1,"method":"heartbeat","params":{"session":"0123"}}'
        async with (
            aiohttp.ClientSession() as session,
            session.ws_connect(f"http://127.0.0.1:{port}/ws") as ws,
        ):
            for index in range(CALLS + 100):
                started = time.perf_counter()
                await ws.send_str(request)
                await ws.receive()
                if index >= 100:
                    samples.append((time.perf_counter() - started) * 1000)
    finally:
        server.kill()
        await server.wait()
    return samples


async def run() -> dict[str, Any]:
    ours, extra = await _brasidas_round_trips()
    port = free_port()
    server = await asyncio.create_subprocess_exec(
        sys.executable, "-c", PYRO_SERVER, str(port), stdout=asyncio.subprocess.PIPE
    )
    try:
        assert server.stdout is not None
        await asyncio.wait_for(server.stdout.readline(), 10)
        pyro = await asyncio.to_thread(_pyro_round_trips, port)
    finally:
        server.kill()
        await server.wait()
    floor = percentiles(await _aiohttp_echo_floor())
    mine, theirs = percentiles(ours), percentiles(pyro)
    return {
        "ws_jsonrpc_heartbeat_p50_ms": mine["p50"],
        "ws_jsonrpc_heartbeat_p99_ms": mine["p99"],
        "pyro5_call_p50_ms": theirs["p50"],
        "pyro5_call_p99_ms": theirs["p99"],
        "p50_ratio_vs_pyro5": round(mine["p50"] / theirs["p50"], 2),
        "aiohttp_ws_echo_floor_p50_ms": floor["p50"],
        "aiohttp_ws_echo_floor_p99_ms": floor["p99"],
        "target": "p50 <= 0.7x Pyro5, p99 < 1 ms",
        **extra,
    }
