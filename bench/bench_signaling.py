"""Signaling round trip (WebSocket JSON-RPC vs a Pyro5 proxy and a bare aiohttp echo),
shutdown time, idle RSS (--sim with its demo map, and without a map: no Shapely/NumPy)."""

from __future__ import annotations

import asyncio
import json
import signal
import sys
import time
from collections.abc import Awaitable, Callable
from typing import Any

from bench.support import (
    connect_to_platform,
    free_port,
    percentiles,
    rss_mb,
    start_platform,
    stop_process,
    wait_ready,
)
from brasidas.codecs.jsonrpc import request_text
from stationd.client import PlatformConnection

CALLS = 5000

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


ROUNDS = 25
"""The three are measured in alternating rounds of CALLS / ROUNDS calls, so a change in the
machine's load or clock speed during the bench touches all three alike."""

ECHO_SERVER = """
import asyncio, sys
from aiohttp import web
ANSWER = sys.argv[2]
async def ws(request):
    socket = web.WebSocketResponse()
    await socket.prepare(request)
    async for message in socket:
        await socket.send_str(ANSWER)
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
"""The floor: a bare aiohttp WebSocket server that answers every message with a fixed text
(the heartbeat's answer, byte for byte the size the platform sends), to a client that sends
the heartbeat's very request text: same sizes both ways, same loopback TCP, same library on
both ends (aiohttp's WebSocketResponse and ClientSession.ws_connect), no JSON on either end."""


Call = Callable[[], Awaitable[object]]


async def _timed(call: Call, count: int, samples: list[float]) -> None:
    for _ in range(count):
        started = time.perf_counter()
        await call()
        samples.append((time.perf_counter() - started) * 1000)


async def _server(script: str, *args: str) -> tuple[asyncio.subprocess.Process, int]:
    port = free_port()
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-c", script, str(port), *args, stdout=asyncio.subprocess.PIPE
    )
    assert process.stdout is not None
    await asyncio.wait_for(process.stdout.readline(), 10)
    return process, port


async def _measure(connection: PlatformConnection) -> tuple[dict[str, list[float]], str, str]:
    """Heartbeats over our WebSocket, a Pyro5 proxy's trivial call, the bare aiohttp floor;
    and the request and answer texts the floor exchanges (the heartbeat's own)."""
    import aiohttp
    import Pyro5.api

    async def ours() -> object:
        return await connection.call("heartbeat")

    # The texts our heartbeat puts on the wire (ids of the width the measured calls use).
    request = request_text("heartbeat", {"session": connection.session_id}, CALLS)
    answer = json.dumps(
        {"jsonrpc": "2.0", "id": CALLS, "result": await ours()}, separators=(",", ":")
    )
    pyro_server, pyro_port = await _server(PYRO_SERVER)
    echo_server, echo_port = await _server(ECHO_SERVER, answer)
    try:
        async with (
            aiohttp.ClientSession() as session,
            session.ws_connect(f"http://127.0.0.1:{echo_port}/ws") as ws,
        ):
            with Pyro5.api.Proxy(f"PYRO:target@127.0.0.1:{pyro_port}") as proxy:

                async def pyro() -> object:
                    # A blocking call on the loop: nothing else of the bench runs meanwhile,
                    # and a thread hop would only add to Pyro5's figure.
                    return proxy.heartbeat()

                async def echo() -> object:
                    await ws.send_str(request)
                    return await ws.receive()

                calls = {"ours": ours, "pyro5": pyro, "echo": echo}
                samples: dict[str, list[float]] = {name: [] for name in calls}
                for call in calls.values():
                    await _timed(call, 100, [])  # warm-up
                for _ in range(ROUNDS):
                    for name, call in calls.items():
                        await _timed(call, CALLS // ROUNDS, samples[name])
                return samples, request, answer
    finally:
        for server in (pyro_server, echo_server):
            server.kill()
            await server.wait()


async def _idle_rss_without_map() -> float:
    """A --sim platform without a map (no demo map either): no Shapely, no NumPy."""
    port = free_port()
    process = await start_platform(
        f"signaling.port={port}", "sim.demo_map=false", "map.file=/nonexistent/map.geojson"
    )
    try:
        await wait_ready(port)
        await asyncio.sleep(1.0)
        return rss_mb(process.pid)
    finally:
        await stop_process(process)


async def run() -> dict[str, Any]:
    figures: dict[str, Any] = {"platform_rss_idle_no_map_mb": await _idle_rss_without_map()}
    port = free_port()
    process = await start_platform(f"signaling.port={port}")
    try:
        await wait_ready(port)
        await asyncio.sleep(1.0)  # let start-up settle before measuring idle memory
        figures["platform_rss_idle_mb"] = rss_mb(process.pid)
        connection = await connect_to_platform(port)
        try:
            samples, request, answer = await _measure(connection)
        finally:
            await connection.close()
        sent = time.perf_counter()
        process.send_signal(signal.SIGTERM)
        await asyncio.wait_for(process.wait(), 5)
        figures["platform_sigterm_exit_ms"] = round((time.perf_counter() - sent) * 1000, 1)
        figures["platform_sigterm_exit_status"] = process.returncode
    finally:
        if process.returncode is None:
            process.kill()
            await process.wait()
    mine, theirs = percentiles(samples["ours"]), percentiles(samples["pyro5"])
    floor = percentiles(samples["echo"])
    return {
        "ws_jsonrpc_heartbeat_p50_ms": mine["p50"],
        "ws_jsonrpc_heartbeat_p99_ms": mine["p99"],
        "pyro5_call_p50_ms": theirs["p50"],
        "pyro5_call_p99_ms": theirs["p99"],
        "p50_ratio_vs_pyro5": round(mine["p50"] / theirs["p50"], 2),
        "aiohttp_ws_echo_floor_p50_ms": floor["p50"],
        "aiohttp_ws_echo_floor_p99_ms": floor["p99"],
        "p50_ratio_vs_echo": round(mine["p50"] / floor["p50"], 3),
        "floor": "bare aiohttp WebSocket server answering a fixed text; client sends with"
        " ws.send_str and reads with ws.receive in one task (aiohttp both ends, loopback TCP)",
        "request_bytes": len(request),
        "answer_bytes": len(answer),
        "rounds": ROUNDS,
        "target": "p50 <= 1.10x the bare aiohttp echo of the same run and <= 0.7x Pyro5, p99 < 1 ms",
        **figures,
    }
