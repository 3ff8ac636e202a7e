"""Issue 19: a host without the fleet key gets bounded work from the platform and the station.

A platform and a station on loopback, each attacked the way the issue did: batches of ``{}``,
lone surrogates, half-sent headers, readers that never read, unknown platform ids. Attackers
use their own loopback address (127.0.0.2, ...): the caps are per source address, and the
station under test connects from 127.0.0.1. The platform as a process under a lowered open-file
limit: tests/test_hostile_process.py.
"""

from __future__ import annotations

import asyncio
import base64
import json
import os
import socket
import struct
import sys
from collections.abc import Awaitable, Callable
from pathlib import Path

import aiohttp
import pytest
from conftest import quiet_platform_config, running_station, wait_until

from brasidas.codecs.jsonrpc import encode_request
from platformd.app import PlatformDaemon
from stationd.client import PlatformConnection
from stationd.connections import ConnectionManager
from stationd.daemon import StationDaemon

Factory = Callable[..., Awaitable[PlatformDaemon]]

REPOSITORY = Path(__file__).resolve().parent.parent
"""Where ``python -m bench.hostile_peer`` runs from."""

FLOOD = b"[" + b",".join([b"{}"] * 21_000) + b"]"
"""The issue's batch: 21,000 empty objects in 64 KiB."""


# --------------------------------------------------------------------------- the platform


def stranger_socket(address: tuple[str, int], source: str = "127.0.0.2") -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind((source, 0))
    sock.connect(address)
    return sock


def signaling_address(daemon: PlatformDaemon) -> tuple[str, int]:
    host, port = daemon.ctx.signaling_url.removeprefix("http://").rsplit(":", 1)
    return host, int(port)


def counters(daemon: PlatformDaemon) -> dict[str, int]:
    """Signaling's admission counters."""
    admission = daemon.ctx.signaling_admission
    assert admission is not None
    return admission.counters()


async def post(url: str, body: bytes) -> tuple[int, bytes]:
    async with aiohttp.ClientSession() as session, session.post(url, data=body) as response:
        return response.status, await response.read()


async def test_a_strangers_batch_flood_is_one_short_error(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    """Defect 3: a 64 KiB batch of 21,000 ``{}`` was answered item by item (1.7 MB each)."""
    daemon = await platform_factory(quiet_platform_config(), fleet_key)
    url = daemon.ctx.signaling_url + "/rpc"
    status, body = await post(url, FLOOD)
    assert len(body) < 1024, f"{len(body)} bytes answered to a stranger"
    assert status == 413  # over the 4 KiB a stranger may send: not even parsed
    small = b"[" + b",".join([b"{}"] * 500) + b"]"
    status, body = await post(url, small)
    answer = json.loads(body)
    assert isinstance(answer, dict)
    assert answer["error"]["code"] == -32600
    challenge = {"jsonrpc": "2.0", "method": "challenge"}
    batch = [{**challenge, "id": 1}, {**challenge, "id": 2}]
    status, body = await post(url, json.dumps(batch).encode())  # what needs no session: served
    assert status == 200
    assert [item["id"] for item in json.loads(body)] == [1, 2]
    heartbeats = [
        {"jsonrpc": "2.0", "id": n, "method": "heartbeat", "params": {"session": "x"}}
        for n in range(3)
    ]
    status, body = await post(url, json.dumps(heartbeats).encode())
    assert "before a session" in json.loads(body)["error"]["message"]
    assert daemon.ctx.rpc.counters["unauthorized"] == 0  # refused before any was tried


async def test_a_batch_is_capped_even_for_a_session(platform_factory: Factory) -> None:
    daemon = await platform_factory(quiet_platform_config(), None)  # connect needs no proof
    async with (
        aiohttp.ClientSession() as session,
        session.ws_connect(daemon.ctx.signaling_url + "/rpc/ws") as ws,
    ):
        await ws.send_str(encode_request("connect", ["st-1"], 1).decode())
        token = json.loads((await ws.receive(timeout=10)).data)["result"]["session"]
        heartbeat = {"jsonrpc": "2.0", "method": "heartbeat", "params": {"session": token}}
        await ws.send_str(json.dumps([{**heartbeat, "id": n} for n in range(100)]))
        assert len(json.loads((await ws.receive(timeout=10)).data)) == 100
        await ws.send_str(json.dumps([{**heartbeat, "id": n} for n in range(101)]))
        answer = json.loads((await ws.receive(timeout=10)).data)
        assert answer["error"]["code"] == -32600
        assert "at most 100" in answer["error"]["message"]


@pytest.mark.parametrize("field", ["station_id", "station_nonce", "proof"])
async def test_a_lone_surrogate_in_connect_is_invalid_params(
    platform_factory: Factory, fleet_key: bytes, field: str
) -> None:
    """Defect 9: ``"\\ud800"`` decodes to a lone surrogate, which cannot be encoded: -32603."""
    daemon = await platform_factory(quiet_platform_config(), fleet_key)
    url = daemon.ctx.signaling_url + "/rpc"
    _, body = await post(url, encode_request("challenge", None, 1))
    params = {"station_id": "st", "nonce": json.loads(body)["result"]["nonce"]}
    params |= {"station_nonce": "00", "proof": "00", field: "\ud800"}
    request = {"jsonrpc": "2.0", "id": 2, "method": "connect", "params": params}
    _, body = await post(url, json.dumps(request).encode())  # sent as the escape
    answer = json.loads(body)
    assert answer["error"]["code"] == -32602, answer
    assert daemon.ctx.rpc.counters["internal_errors"] == 0


async def test_half_sent_headers_are_closed_within_the_header_timeout(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    """Defect 2: partial headers or bodies stayed open indefinitely."""
    # Scaled down from 5 s each: what is tested is that they are applied.
    config = quiet_platform_config("admission.header_timeout=1", "admission.body_timeout=1")
    daemon = await platform_factory(config, fleet_key)
    address = signaling_address(daemon)
    partial_headers = [stranger_socket(address) for _ in range(4)]
    partial_bodies = [stranger_socket(address, "127.0.0.3") for _ in range(4)]
    try:
        for sock in partial_headers:
            sock.sendall(b"POST /rpc HTTP/1.1\r\nHost: x\r\n")
        for sock in partial_bodies:
            sock.sendall(b"POST /rpc HTTP/1.1\r\nHost: x\r\nContent-Length: 100\r\n\r\n{")

        sockets = partial_headers + partial_bodies
        ended = await asyncio.gather(*(ends_within(sock, 20) for sock in sockets))
        assert all(ended)  # a 408 for a body, then the end
    finally:
        for sock in partial_headers + partial_bodies:
            sock.close()
    closed = counters(daemon)
    assert closed["header_timeouts"] == 4
    assert closed["body_timeouts"] == 4


async def ends_within(sock: socket.socket, timeout: float) -> bool:
    """The server closed ``sock`` within ``timeout`` (whatever it sent first)."""
    sock.setblocking(False)
    loop = asyncio.get_running_loop()
    try:
        async with asyncio.timeout(timeout):
            while await loop.sock_recv(sock, 4096):
                pass
    except TimeoutError:
        return False
    except ConnectionResetError:
        pass
    return True


def closed(watchers: list[asyncio.Task[bool]]) -> int:
    """How many of the :func:`ends_within` watchers saw their socket closed so far."""
    return sum(1 for watcher in watchers if watcher.done() and watcher.result())


async def test_idle_strangers_are_capped_and_a_station_still_connects(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    """Defect 2 in small: one host's idle connections hold no more than its cap."""
    daemon = await platform_factory(quiet_platform_config(), fleet_key)
    address = signaling_address(daemon)
    idle = [stranger_socket(address) for _ in range(40)]
    try:
        # All but the host's 8 are closed at once; the 8 stay (their idle timeout is 15 s).
        watchers = [asyncio.create_task(ends_within(sock, 10)) for sock in idle]
        try:
            await wait_until(lambda: closed(watchers) >= 32, 10)
            await asyncio.sleep(0.5)  # a window to watch, not a synchronisation
            assert closed(watchers) == 32
        finally:
            for watcher in watchers:
                watcher.cancel()
            await asyncio.gather(*watchers, return_exceptions=True)
        conn = PlatformConnection(
            "brasidas-1", daemon.ctx.signaling_url, station_id="st-1", fleet_key=fleet_key
        )
        await conn.open()
        await conn.close()
    finally:
        for sock in idle:
            sock.close()


async def websocket_handshake(
    address: tuple[str, int], path: str, rcvbuf: int = 4096
) -> socket.socket:
    """A raw WebSocket client with a tiny receive buffer (it will never read) and a small send
    buffer: a flood's requests wait in the client, not 4 MB of them in its kernel, which the
    server read and answered (~6 s) before its own unsent answers could start to stall."""
    loop = asyncio.get_running_loop()
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4096)
    sock.setblocking(False)
    await loop.sock_connect(sock, address)
    key = base64.b64encode(os.urandom(16)).decode()
    request = (
        f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{address[1]}\r\nUpgrade: websocket\r\n"
        f"Connection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
    )
    await loop.sock_sendall(sock, request.encode())
    reply = b""
    while b"\r\n\r\n" not in reply:
        reply += await asyncio.wait_for(loop.sock_recv(sock, 1), 10)
    assert reply.startswith(b"HTTP/1.1 101"), reply
    return sock


def ws_frame(text: str) -> bytes:
    """A masked text frame (a zero mask: the payload as it is)."""
    payload = text.encode()
    size = len(payload)
    if size < 126:
        header = struct.pack("!BB", 0x81, 0x80 | size)
    elif size < 65536:
        header = struct.pack("!BBH", 0x81, 0x80 | 126, size)
    else:
        header = struct.pack("!BBQ", 0x81, 0x80 | 127, size)
    return header + b"\0\0\0\0" + payload


async def closed_while_flooding(sock: socket.socket, frame: bytes, timeout: float) -> bool:
    """Send ``frame`` again and again, never reading: True once the server closed."""
    sock.setblocking(False)
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    pending = b""
    while loop.time() < deadline:
        pending = pending or frame  # whole frames only: a partial send is finished first
        try:
            pending = pending[sock.send(pending) :]
        except BlockingIOError:
            await asyncio.sleep(0.02)
        except (ConnectionResetError, BrokenPipeError):
            return True
    return False


async def test_a_websocket_that_never_reads_is_closed(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    """Defect 3: WebSockets that never read grew the platform by 2.7 MB each, for good. A
    station's (a stranger's is not even read past its byte budget)."""
    # The write timeout scaled down from 10 s: what is tested is that it is applied.
    config = quiet_platform_config("admission.write_timeout=2")
    daemon = await platform_factory(config, None)  # connect needs no proof
    sock = await websocket_handshake(signaling_address(daemon), "/rpc/ws")
    try:
        await asyncio.get_running_loop().sock_sendall(
            sock, ws_frame(encode_request("connect", ["reader"], 0).decode())
        )
        challenge = encode_request("challenge", None, 1).decode()
        assert await closed_while_flooding(sock, ws_frame(challenge), 40)
    finally:
        sock.close()
    assert counters(daemon)["slow_readers"] >= 1


# --------------------------------------------------------------------------- the station


def station_rpc(station: StationDaemon) -> str:
    return f"http://127.0.0.1:{station.api_port}/api/rpc"


async def test_the_local_api_answers_a_batch_flood_with_one_error(
    station: StationDaemon,
) -> None:
    _, body = await post(station_rpc(station), FLOOD)
    answer = json.loads(body)
    assert isinstance(answer, dict), len(body)
    assert answer["error"]["code"] == -32600, len(body)


async def test_unknown_platform_ids_cost_the_station_nothing(station: StationDaemon) -> None:
    """Defect 7: a lock per id asked about, never released; ids of any length."""
    manager = station.ctx.connection_manager
    assert isinstance(manager, ConnectionManager)
    url = station_rpc(station)
    for number in range(50):
        _, body = await post(url, encode_request("status", [f"ghost-{number}"], number))
        assert json.loads(body)["error"]["code"] == -32002  # not discovered
    assert manager._connecting == {}
    huge = "x" * 30_000
    _, body = await post(url, encode_request("status", [huge], 99))
    error = json.loads(body)["error"]
    assert error["code"] == -32602
    assert "longer than 64" in error["message"]
    assert manager._connecting == {}


async def test_a_local_websocket_that_never_reads_is_closed(fleet_key: bytes) -> None:
    async with running_station(fleet_key, "admission.write_timeout=2") as station:
        sock = await websocket_handshake(("127.0.0.1", station.api_port), "/api/rpc/ws")
        try:
            flood = ws_frame(encode_request("connections", None, 1).decode())
            assert await closed_while_flooding(sock, flood, 40)
        finally:
            sock.close()
        assert station.api_admission is not None
        assert station.api_admission.counters()["slow_readers"] >= 1, str(
            station.api_admission.counters()
        )


async def test_a_strangers_flood_at_full_rate_is_read_at_its_budget(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    """Defect 3 at full rate: 4 connections posting the 64 KiB batch as fast as answered
    (bench/hostile_peer.py, its own process) got 247 MB of answers in 10 s and stalled the
    platform's loop; now one address's strangers are read at ``stranger_bytes_per_s``."""
    daemon = await platform_factory(quiet_platform_config(), fleet_key)
    host, port = signaling_address(daemon)
    attacker = await asyncio.create_subprocess_exec(
        *(sys.executable, "-m", "bench.hostile_peer", "flood", host, str(port), "3", "4"),
        stdout=asyncio.subprocess.PIPE,
        cwd=REPOSITORY,
    )
    out, _ = await asyncio.wait_for(attacker.communicate(), 60)
    figures = json.loads(out.decode().splitlines()[-1])
    assert figures["answered_bytes"] < 16_384, figures
    assert counters(daemon)["throttled"] >= 1


async def test_a_station_behind_the_address_of_a_stranger_at_its_cap_still_connects(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    """NAT: the station and a stranger share 127.0.0.1, which holds its 8 idle stranger
    connections. The station's connection gets its chance (the address's oldest stranger,
    held over a second, goes) and, once it has proven the key, is no stranger's: more
    strangers from the same address, or filling the platform's whole stranger pool, never
    close it."""
    daemon = await platform_factory(
        quiet_platform_config("admission.max_strangers=16", "signaling.heartbeat_interval=0.2"),
        fleet_key,
    )
    admission = daemon.ctx.signaling_admission
    assert admission is not None
    address = signaling_address(daemon)
    idle = [stranger_socket(address, source="127.0.0.1") for _ in range(8)]
    conn = PlatformConnection(
        "brasidas-1", daemon.ctx.signaling_url, station_id="st-1", fleet_key=fleet_key
    )
    try:
        await wait_until(lambda: admission.stranger_count() == 8)
        policy = admission.listeners[0].policy
        loop = asyncio.get_running_loop()
        oldest = policy.strangers["127.0.0.1"][0]
        await wait_until(lambda: loop.time() - oldest.opened > policy.limits.host_evict_after)
        async with asyncio.timeout(10):
            await conn.open()
        assert await ends_within(idle[0], 5)  # the oldest stranger made room
        assert admission.stranger_count() == 7  # the station is none of them
        more = [stranger_socket(address, source="127.0.0.1") for _ in range(8)]
        more += [stranger_socket(address, source=f"127.0.0.{n}") for n in (3, 4) for _ in range(8)]
        idle += more
        await wait_until(lambda: admission.counters()["accepted"] >= 33)
        assert admission.stranger_count() == 16  # the pool is full...
        for _ in range(3):  # ...and the station's session goes on
            await conn.call("heartbeat")
        assert not conn.closed.is_set()
    finally:
        await conn.close()
        for sock in idle:
            sock.close()
