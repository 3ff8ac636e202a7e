"""The JSON-RPC clients (the platform's WebSocket client and the station's local-API client)
against real servers that answer badly: a bad answer is dropped and counted, never fatal."""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

import pytest
from aiohttp import web
from conftest import wait_until

from brasidas.actor import Supervisor
from brasidas.bus import Bus
from brasidas.codecs.jsonrpc import INTERNAL_ERROR, TIMEOUT, RpcError
from brasidas.config import StationConfig, load_config
from brasidas.rpc import RpcClient, serve_app
from stationd.api_client import api_call_async

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]
Script = Callable[[int], list[str]]
"""Given a request's id, the raw messages the server sends back."""


class ScriptedServer:
    """A WebSocket and an HTTP endpoint whose answers a test writes by hand."""

    def __init__(self) -> None:
        self.script: Script = lambda request_id: []
        self.url = ""

    async def websocket(self, request: web.Request) -> web.StreamResponse:
        ws = web.WebSocketResponse()
        await ws.prepare(request)
        async for message in ws:
            for raw in self.script(json.loads(message.data)["id"]):
                await ws.send_str(raw)
        return ws

    async def post(self, request: web.Request) -> web.Response:
        request_id = json.loads(await request.read())["id"]
        return web.Response(text=self.script(request_id)[0], content_type="application/json")


@contextlib.asynccontextmanager
async def serving(websocket: Handler, post: Handler | None = None) -> AsyncIterator[str]:
    """A real server on loopback with ``websocket`` at ``/ws`` (and ``post`` at ``/api/rpc``):
    its base URL, for the block's lifetime."""
    app = web.Application()
    app.router.add_get("/ws", websocket)
    if post is not None:
        app.router.add_post("/api/rpc", post)
    supervisor = Supervisor()
    port = await serve_app(app, "127.0.0.1", 0, supervisor=supervisor, bus=Bus(), name="test")
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        await supervisor.stop(2.0)


@pytest.fixture
async def server() -> AsyncIterator[ScriptedServer]:
    scripted = ScriptedServer()
    async with serving(scripted.websocket, scripted.post) as scripted.url:
        yield scripted


def ok(request_id: int, result: Any = "fine") -> str:
    return json.dumps({"jsonrpc": "2.0", "id": request_id, "result": result})


BAD_ANSWERS: list[Callable[[int], str]] = [
    lambda i: json.dumps({"jsonrpc": "2.0", "id": [i], "result": 1}),  # was TypeError
    lambda i: json.dumps({"jsonrpc": "2.0", "id": {"x": i}, "result": 1}),
    lambda i: json.dumps({"jsonrpc": "2.0", "id": float(i), "result": 1}),
    lambda i: json.dumps({"jsonrpc": "2.0", "id": True, "result": 1}),
    lambda i: '{"jsonrpc":"2.0","id":1e999,"result":1}',
    lambda i: "[7]",
    lambda i: "not json",
    lambda i: "[" * 100_000,
    lambda i: f'{{"jsonrpc":"2.0","id":{i},"result":NaN}}',
    lambda i: f'{{"jsonrpc":"2.0","id":{i},"result":1e999}}',
]
"""Answers that name no call of ours: dropped and counted; the real answer still arrives."""

MALFORMED_FOR_A_CALL: list[Callable[[int], str]] = [
    lambda i: json.dumps({"jsonrpc": "2.0", "id": i, "error": {"code": "x", "message": "m"}}),
    lambda i: json.dumps({"jsonrpc": "2.0", "id": i, "error": {"code": 1.5}}),
    lambda i: json.dumps({"jsonrpc": "2.0", "id": i, "error": {"code": 1, "message": 7}}),
    lambda i: json.dumps({"jsonrpc": "2.0", "id": i, "error": "broken"}),
    lambda i: json.dumps({"jsonrpc": "2.0", "id": i}),
]
"""Answers that name a call but cannot be read: that call fails at once, the client lives."""


async def test_answers_that_name_no_call_are_dropped_and_counted(server: ScriptedServer) -> None:
    server.script = lambda i: [bad(i) for bad in BAD_ANSWERS] + [ok(i)]
    async with RpcClient(server.url + "/ws", timeout=10) as client:
        assert await client.call("anything") == "fine"
        assert await client.call("again") == "fine"
        assert client.bad_answers == 2 * len(BAD_ANSWERS)
        assert not client.closed.is_set()


@pytest.mark.parametrize("bad", MALFORMED_FOR_A_CALL)
async def test_a_malformed_answer_fails_its_call_and_the_reader_goes_on(
    server: ScriptedServer, bad: Callable[[int], str]
) -> None:
    server.script = lambda i: [bad(i)] if i == 1 else [ok(i)]
    async with RpcClient(server.url + "/ws", timeout=10) as client:
        with pytest.raises(RpcError) as failed:
            await client.call("first")
        assert failed.value.code == INTERNAL_ERROR
        assert "malformed" in failed.value.message
        assert await client.call("second") == "fine"  # the reader task is still alive
        assert client.bad_answers == 1


async def test_an_error_answer_is_raised_with_its_code(server: ScriptedServer) -> None:
    error = {"code": -32002, "message": "no camera", "data": {"hint": 1}}
    server.script = lambda i: [json.dumps({"jsonrpc": "2.0", "id": i, "error": error})]
    async with RpcClient(server.url + "/ws", timeout=10) as client:
        with pytest.raises(RpcError) as failed:
            await client.call("camera")
        assert (failed.value.code, failed.value.message, failed.value.data) == (
            -32002,
            "no camera",
            {"hint": 1},
        )
        assert client.bad_answers == 0


def _station_config(server: ScriptedServer) -> StationConfig:
    port = server.url.rsplit(":", 1)[1]
    return load_config(
        StationConfig, None, ["station.api_host=127.0.0.1", f"station.api_port={port}"]
    )


@pytest.mark.parametrize("bad", [*BAD_ANSWERS, *MALFORMED_FOR_A_CALL, lambda i: "[]"])
async def test_the_local_api_client_reads_answers_the_same_way(
    server: ScriptedServer, bad: Callable[[int], str]
) -> None:
    server.script = lambda i: [bad(i)]
    with pytest.raises(RpcError) as failed:
        await asyncio.wait_for(api_call_async(_station_config(server), "status"), 10)
    assert failed.value.code == INTERNAL_ERROR
    server.script = lambda i: [ok(i, {"platforms": []})]
    assert await api_call_async(_station_config(server), "status") == {"platforms": []}


async def test_a_call_without_answer_times_out_and_the_next_one_is_answered(
    server: ScriptedServer,
) -> None:
    server.script = lambda i: [] if i <= 2 else [ok(i)]
    async with RpcClient(server.url + "/ws", timeout=30) as client:
        slow = asyncio.ensure_future(client.call("long", timeout=30))
        with pytest.raises(RpcError) as failed:  # a shorter limit after a longer one
            await client.call("short", timeout=0.2)
        assert failed.value.code == TIMEOUT
        assert "short within 0.2 s" in failed.value.message
        assert not slow.done()
        assert await client.call("third") == "fine"
        slow.cancel()
        with pytest.raises(asyncio.CancelledError):
            await slow


async def test_a_fast_path_call_without_answer_times_out_and_the_socket_goes_on(
    server: ScriptedServer,
) -> None:
    """Back to back, the second call reads its own answer (nobody else is receiving): its
    timeout must still end it, and receiving must go on for the next call."""
    server.script = lambda i: [] if i == 2 else [ok(i)]
    async with RpcClient(server.url + "/ws", timeout=30) as client:
        assert await client.call("first") == "fine"
        with pytest.raises(RpcError) as failed:
            await client.call("silent", timeout=0.2)
        assert failed.value.code == TIMEOUT
        assert await client.call("third") == "fine"
        assert not client.closed.is_set()


async def test_a_cancelled_fast_path_call_is_cancelled_and_the_next_call_is_answered(
    server: ScriptedServer,
) -> None:
    server.script = lambda i: [] if i == 2 else [ok(i)]
    async with RpcClient(server.url + "/ws", timeout=30) as client:
        assert await client.call("first") == "fine"
        with pytest.raises(TimeoutError):  # the caller's own limit: a cancellation inside
            async with asyncio.timeout(0.2):
                await client.call("silent")
        assert await client.call("third") == "fine"
        late = asyncio.ensure_future(client.call("fourth"))
        assert await late == "fine"


async def test_concurrent_calls_from_many_tasks_get_their_own_answers() -> None:
    """Answers come back out of order, after random delays: whichever task is receiving,
    every call gets its own answer."""
    import random

    async def websocket(request: web.Request) -> web.StreamResponse:
        ws = web.WebSocketResponse()
        await ws.prepare(request)

        async def answer(message: dict[str, Any]) -> None:
            await asyncio.sleep(random.uniform(0, 0.01))
            await ws.send_str(ok(message["id"], message["params"]))

        async with asyncio.TaskGroup() as group:
            async for message in ws:
                group.create_task(answer(json.loads(message.data)))
        return ws

    async with serving(websocket) as url, RpcClient(url + "/ws", timeout=10) as client:

        async def caller(name: int) -> list[Any]:
            return [await client.call("echo", [name, n]) for n in range(20)]

        results = await asyncio.gather(*(caller(name) for name in range(8)))
        assert results == [[[name, n] for n in range(20)] for name in range(8)]
        assert client.bad_answers == 0


async def test_the_end_of_the_connection_is_noticed_while_idle_and_mid_call(
    server: ScriptedServer,
) -> None:
    """The server goes away: a call reading its own answer fails with ConnectionError, and an
    idle client notices too (``closed``), with nobody calling."""
    closing: list[web.WebSocketResponse] = []

    async def websocket(request: web.Request) -> web.StreamResponse:
        ws = web.WebSocketResponse()
        await ws.prepare(request)
        closing.append(ws)
        async for message in ws:
            request_id = json.loads(message.data)["id"]
            if request_id == 2:
                await ws.close()  # mid-call, instead of an answer
            else:
                await ws.send_str(ok(request_id))
        return ws

    async with serving(websocket) as url:
        async with RpcClient(url + "/ws", timeout=10) as client:
            assert await client.call("first") == "fine"
            with pytest.raises(ConnectionError):
                await client.call("second")  # the fast path: it was reading
            await asyncio.wait_for(client.closed.wait(), 5)
        async with RpcClient(url + "/ws", timeout=10) as client:
            assert await client.call("first") == "fine"
            await closing[-1].close()  # nobody calls now: the reader must notice
            await asyncio.wait_for(client.closed.wait(), 5)
            with pytest.raises(ConnectionError):
                await client.call("after")


async def test_an_unsolicited_message_while_idle_is_counted_and_dropped(
    server: ScriptedServer,
) -> None:
    server.script = lambda i: [ok(i), ok(i + 1000)] if i == 1 else [ok(i)]
    async with RpcClient(server.url + "/ws", timeout=10) as client:
        assert await client.call("first") == "fine"  # then an answer to nobody, while idle
        assert await client.call("second") == "fine"
        server.script = lambda i: [ok(i), "not json"]
        assert await client.call("third") == "fine"
        await wait_until(lambda: client.bad_answers == 1)
        assert not client.closed.is_set()
