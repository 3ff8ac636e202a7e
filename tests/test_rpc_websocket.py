"""The JSON-RPC WebSocket transport: a method that waits does not hold up the ones behind it;
malformed input is answered on a socket that stays open."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Any

import aiohttp
import pytest
from aiohttp import web
from conftest import quiet_platform_config

from brasidas.actor import Supervisor
from brasidas.bus import Bus
from brasidas.codecs.jsonrpc import CallContext, Dispatcher, encode_request
from brasidas.rpc import RpcClient, add_rpc_routes, serve_app
from platformd.app import PlatformDaemon


class SlowService:
    """``slow`` waits until released (as a command waits for its actor); ``ping`` answers."""

    def __init__(self) -> None:
        self.release = asyncio.Event()
        self.started = asyncio.Event()
        self.cancelled = asyncio.Event()

    async def slow(self, call: CallContext) -> str:
        self.started.set()
        try:
            await self.release.wait()
        except asyncio.CancelledError:
            self.cancelled.set()
            raise
        return "done"

    def ping(self, call: CallContext) -> str:
        return "pong"

    def reading(self, call: CallContext) -> dict[str, float]:
        return {"pitch": float("nan"), "roll": 0.5}  # a sensor that failed


@pytest.fixture
async def served() -> AsyncIterator[tuple[str, SlowService]]:
    service = SlowService()
    dispatcher = Dispatcher()
    dispatcher.add("slow", service.slow, session_required=False)
    dispatcher.add("ping", service.ping, session_required=False)
    dispatcher.add("reading", service.reading, session_required=False)
    app = web.Application()
    add_rpc_routes(app, dispatcher, "/rpc", 65536)
    supervisor = Supervisor()
    port = await serve_app(app, "127.0.0.1", 0, supervisor=supervisor, bus=Bus(), name="rpc")
    yield f"http://127.0.0.1:{port}/rpc/ws", service
    await supervisor.stop(2.0)


def test_plain_functions_answer_at_once_and_coroutines_may_wait() -> None:
    dispatcher = Dispatcher()
    service = SlowService()
    dispatcher.add("slow", service.slow, session_required=False)
    dispatcher.add("ping", service.ping, session_required=False)

    def at_once(message: Any) -> bool:
        return dispatcher.answers_at_once(dispatcher.parse(json.dumps(message)))

    assert at_once({"jsonrpc": "2.0", "id": 1, "method": "ping"})
    assert not at_once({"jsonrpc": "2.0", "id": 1, "method": "slow"})
    assert at_once({"jsonrpc": "2.0", "id": 1, "method": "nope"})  # answers an error at once
    assert not at_once([{"jsonrpc": "2.0", "id": 1, "method": "ping"}])  # a batch may wait
    assert dispatcher.answers_at_once(dispatcher.parse(b"{not json"))


async def test_a_waiting_method_does_not_hold_up_the_next_request(
    served: tuple[str, SlowService],
) -> None:
    url, service = served
    async with RpcClient(url, timeout=10) as client:
        slow = asyncio.ensure_future(client.call("slow"))
        await asyncio.wait_for(service.started.wait(), 10)
        # Same socket, sent after: answered while "slow" is still waiting.
        assert await asyncio.wait_for(client.call("ping"), 10) == "pong"
        assert not slow.done()
        service.release.set()
        assert await asyncio.wait_for(slow, 10) == "done"


async def test_closing_the_socket_cancels_what_is_still_waiting(
    served: tuple[str, SlowService],
) -> None:
    url, service = served
    async with aiohttp.ClientSession() as session:
        ws = await session.ws_connect(url)
        await ws.send_str(encode_request("slow", None, 1).decode())
        await asyncio.wait_for(service.started.wait(), 10)
        await ws.close()
    await asyncio.wait_for(service.cancelled.wait(), 10)


def strict_json(text: str) -> Any:
    """Parse as JSON proper: NaN and Infinity are not JSON."""

    def refuse(name: str) -> Any:
        raise AssertionError(f"{name} in {text!r}")

    return json.loads(text, parse_constant=refuse)


async def ask(ws: aiohttp.ClientWebSocketResponse, raw: str) -> Any:
    await ws.send_str(raw)
    message = await asyncio.wait_for(ws.receive(), 10)
    assert message.type == aiohttp.WSMsgType.TEXT, message
    return strict_json(message.data)


async def test_malformed_requests_are_answered_and_the_session_survives(
    platform_factory: Any,
) -> None:
    daemon: PlatformDaemon = await platform_factory(quiet_platform_config(), None)
    async with (
        aiohttp.ClientSession() as session,
        session.ws_connect(daemon.ctx.signaling_url + "/rpc/ws") as ws,
    ):
        connect = {"jsonrpc": "2.0", "id": 0, "method": "connect", "params": ["st-1"]}
        token = (await ask(ws, json.dumps(connect)))["result"]["session"]
        # An unhashable method name used to raise TypeError outside any handler and close
        # the socket (ending the session, releasing the override).
        for method in ("[1]", '{"a":1}', "null", "1.5"):
            raw = f'{{"jsonrpc":"2.0","method":{method},"id":1}}'
            answer = await ask(ws, raw)
            assert answer["id"] == 1, raw
            assert answer["error"]["code"] == -32600, raw
        # A non-finite id was echoed as Infinity, which is not JSON.
        for raw_id in ("1e999", "-1e999"):
            raw = f'{{"jsonrpc":"2.0","method":"heartbeat","id":{raw_id}}}'
            answer = await ask(ws, raw)
            assert answer["id"] is None, raw
            assert answer["error"]["code"] == -32600, raw
        answer = await ask(ws, '{"jsonrpc":"2.0","method":"heartbeat","id":NaN}')
        assert answer["id"] is None
        assert answer["error"]["code"] == -32700
        heartbeat = {"jsonrpc": "2.0", "id": 2, "method": "heartbeat", "params": {"session": token}}
        assert "manual_override" in (await ask(ws, json.dumps(heartbeat)))["result"]
        assert not ws.closed
        assert token in daemon.ctx.sessions.sessions


async def test_a_result_json_cannot_hold_is_an_internal_error_not_invalid_json(
    served: tuple[str, SlowService],
) -> None:
    url, _ = served
    async with aiohttp.ClientSession() as session, session.ws_connect(url) as ws:
        answer = await ask(ws, encode_request("reading", None, 5).decode())
        assert answer["id"] == 5
        assert answer["error"]["code"] == -32603
        assert "not valid JSON" in answer["error"]["message"]
        batch = [
            {"jsonrpc": "2.0", "id": 6, "method": "reading"},
            {"jsonrpc": "2.0", "id": 7, "method": "ping"},
        ]
        answers = await ask(ws, json.dumps(batch))
        assert [(a["id"], "error" in a) for a in answers] == [(6, True), (7, False)]
        assert (await ask(ws, encode_request("ping", None, 8).decode()))["result"] == "pong"


async def test_a_chunked_http_body_is_read_to_its_end(served: tuple[str, SlowService]) -> None:
    url = served[0].removesuffix("/ws")
    request = encode_request("ping", None, 3)

    async def chunks(body: bytes, size: int) -> AsyncIterator[bytes]:
        for start in range(0, len(body), size):  # no Content-Length: chunked, several chunks
            yield body[start : start + size]
            await asyncio.sleep(0.01)

    async with aiohttp.ClientSession() as session:
        async with session.post(url, data=chunks(request, 7)) as response:
            assert response.status == 200
            assert strict_json(await response.text()) == {
                "jsonrpc": "2.0",
                "id": 3,
                "result": "pong",
            }


async def test_a_stopping_server_closes_its_websockets_saying_going_away() -> None:
    """A server that stops closes each open WebSocket with 1001 (going away), so its peer
    learns why at once; it used to wait out its shutdown timeout twice, then cut the
    connection without a close frame (0.4 s of every stop with a station connected)."""
    dispatcher = Dispatcher()
    app = web.Application()
    add_rpc_routes(app, dispatcher, "/rpc", 65536)
    supervisor = Supervisor()
    port = await serve_app(app, "127.0.0.1", 0, supervisor=supervisor, bus=Bus(), name="rpc")
    async with (
        aiohttp.ClientSession() as session,
        session.ws_connect(f"http://127.0.0.1:{port}/rpc/ws") as ws,
    ):
        received = asyncio.create_task(ws.receive())
        await supervisor.stop(2.0)
        message = await received
        assert message.type is aiohttp.WSMsgType.CLOSE, message
        assert message.data == aiohttp.WSCloseCode.GOING_AWAY, message
