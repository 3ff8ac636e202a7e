"""The station's local API refuses what a web page elsewhere could send through the browser."""

from __future__ import annotations

from collections.abc import AsyncIterator

import aiohttp
import pytest

from brasidas.codecs.jsonrpc import encode_request
from brasidas.config import StationConfig, load_config
from stationd.daemon import StationDaemon


@pytest.fixture
async def station(fleet_key: bytes) -> AsyncIterator[StationDaemon]:
    config = load_config(StationConfig, None, ["station.api_port=0", "discovery.port=0"])
    daemon = StationDaemon(config, fleet_key)
    await daemon.start()
    yield daemon
    await daemon.stop()


async def post(url: str, headers: dict[str, str]) -> int:
    async with (
        aiohttp.ClientSession() as session,
        session.post(url, data=encode_request("connections", None, 1), headers=headers) as answer,
    ):
        return answer.status


async def test_same_origin_and_the_cli_are_served(station: StationDaemon) -> None:
    port = station.api_port
    url = f"http://127.0.0.1:{port}/api/rpc"
    assert await post(url, {}) == 200  # the CLI sends no Origin
    assert await post(url, {"Origin": f"http://127.0.0.1:{port}"}) == 200  # the console
    assert await post(f"http://localhost:{port}/api/rpc", {}) == 200


async def test_cross_site_post_and_websocket_are_refused(station: StationDaemon) -> None:
    port = station.api_port
    url = f"http://127.0.0.1:{port}/api/rpc"
    assert await post(url, {"Origin": "https://evil.example"}) == 403
    async with aiohttp.ClientSession() as session:
        with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
            await session.ws_connect(url + "/ws", headers={"Origin": "https://evil.example"})
        assert refused.value.status == 403
        async with session.ws_connect(
            url + "/ws", headers={"Origin": f"http://127.0.0.1:{port}"}
        ) as ws:
            await ws.send_bytes(encode_request("connections", None, 7))
            assert (await ws.receive_json())["result"] == []


async def test_dns_rebinding_host_is_refused(station: StationDaemon) -> None:
    port = station.api_port
    url = f"http://127.0.0.1:{port}/api/rpc"
    # A page at rebound.example resolving to 127.0.0.1: same origin as itself, foreign host.
    headers = {"Host": f"rebound.example:{port}", "Origin": f"http://rebound.example:{port}"}
    assert await post(url, headers) == 403
