"""Issue 26, defect 7: the station's Foxglove WebSocket refuses a foreign Origin or Host with
403, exactly as the console's own WebSocket does; a client sending neither (Foxglove desktop,
a script) still connects and speaks the SDK's protocol."""

from __future__ import annotations

import asyncio

import aiohttp
import pytest
from conftest import running_station

from stationd.foxglove_guard import head_refusal
from stationd.foxglove_live import FoxgloveLive
from stationd.foxglove_subprotocol import LEGACY, SDK, name_legacy, offer_sdk

EVIL = "http://evil.example"


async def upgrade_status(
    url: str, headers: dict[str, str], protocols: tuple[str, ...] = (SDK, LEGACY)
) -> tuple[int, str]:
    """The answer's status to a WebSocket upgrade (101 when accepted) and its subprotocol."""
    async with aiohttp.ClientSession() as http:
        try:
            async with http.ws_connect(url, headers=headers, protocols=protocols) as ws:
                return 101, ws.protocol or ""
        except aiohttp.WSServerHandshakeError as err:
            return err.status, ""


async def test_foreign_origin_and_host_are_refused_like_the_consoles(fleet_key: bytes) -> None:
    async with running_station(fleet_key, "foxglove.port=0") as station:
        (live,) = [a for a in station.supervisor.actors if isinstance(a, FoxgloveLive)]
        await asyncio.wait_for(live.serving.wait(), 30)
        foxglove = f"ws://127.0.0.1:{live.port}/"
        console = f"ws://127.0.0.1:{station.api_port}/api/rpc/ws"
        for url in (foxglove, console):
            assert (await upgrade_status(url, {"Origin": EVIL}))[0] == 403, url
            rebinding = {"Host": f"evil.example:{live.port}"}
            assert (await upgrade_status(url, rebinding))[0] == 403, url
        status, protocol = await upgrade_status(foxglove, {})
        assert status == 101
        assert protocol.startswith("foxglove.")
        own = {"Origin": f"http://127.0.0.1:{live.port}"}
        assert (await upgrade_status(foxglove, own))[0] == 101
        # Only the older name offered: accepted under it (the SDK alone answers 400).
        assert await upgrade_status(foxglove, {}, (LEGACY,)) == (101, LEGACY)
        assert await upgrade_status(foxglove, {}, (SDK,)) == (101, SDK)
        assert live.guard is not None
        assert live.guard.refused == 2
        # The SDK's own server is not on 127.0.0.1, where a page could scan for its port.
        assert live.guard.upstream_host.startswith("127.")
        assert live.guard.upstream_host != "127.0.0.1"


@pytest.mark.parametrize(
    ("head", "refused"),
    [
        (b"GET / HTTP/1.1\r\nHost: 127.0.0.1:8766\r\n\r\n", False),
        (
            b"GET / HTTP/1.1\r\nHost: localhost:8766\r\nOrigin: https://app.foxglove.dev\r\n\r\n",
            False,
        ),
        (b"GET / HTTP/1.1\r\nHost: 127.0.0.1:8766\r\nOrigin: http://evil.example\r\n\r\n", True),
        (b"GET / HTTP/1.1\r\nHost: evil.example\r\n\r\n", True),
        (b"GET / HTTP/1.1\r\n\r\n", True),
        (b"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nHost: evil.example\r\n\r\n", True),
    ],
)
def test_the_head_rule(head: bytes, refused: bool) -> None:
    local = frozenset({"127.0.0.1", "localhost", "[::1]"})
    reason = head_refusal(head, local, ("https://app.foxglove.dev",))
    assert (reason is not None) == refused, reason


def test_only_a_client_offering_just_the_older_name_is_renamed() -> None:
    request = (
        b"GET / HTTP/1.1\r\nHost: 127.0.0.1:8766\r\n"
        b"sec-websocket-protocol: x.v2, foxglove.websocket.v1\r\n\r\n"
    )
    renamed, legacy = offer_sdk(request)
    assert legacy
    assert b"sec-websocket-protocol: x.v2, foxglove.sdk.v1\r\n" in renamed
    assert renamed.endswith(b"\r\n\r\n")
    both = (
        b"GET / HTTP/1.1\r\nSec-WebSocket-Protocol: foxglove.websocket.v1, foxglove.sdk.v1\r\n\r\n"
    )
    assert offer_sdk(both) == (both, False)
    neither = b"GET / HTTP/1.1\r\nSec-WebSocket-Protocol: foxglove.websocket.v10\r\n\r\n"
    assert offer_sdk(neither) == (neither, False)
    answer = (
        b"HTTP/1.1 101 Switching Protocols\r\nsec-websocket-accept: abc=\r\n"
        b"sec-websocket-protocol: foxglove.sdk.v1\r\n\r\n"
    )
    assert name_legacy(answer) == answer.replace(b"foxglove.sdk.v1", b"foxglove.websocket.v1")
