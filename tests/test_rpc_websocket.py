"""The JSON-RPC WebSocket transport: a method that waits does not hold up the ones behind it."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Any

import aiohttp
import pytest
from aiohttp import web

from brasidas.actor import Supervisor
from brasidas.bus import Bus
from brasidas.codecs.jsonrpc import CallContext, Dispatcher, encode_request
from brasidas.rpc import RpcClient, add_rpc_routes, serve_app


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


@pytest.fixture
async def served() -> AsyncIterator[tuple[str, SlowService]]:
    service = SlowService()
    dispatcher = Dispatcher()
    dispatcher.add("slow", service.slow, session_required=False)
    dispatcher.add("ping", service.ping, session_required=False)
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
