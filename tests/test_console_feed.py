"""The console's NavCam feed: the fan-out's rules, and access units over the real WebSocket."""

from __future__ import annotations

import asyncio
import contextlib
import gc
import json
import warnings
from collections.abc import Awaitable, Callable
from typing import Any

import aiohttp
import pytest
from conftest import free_udp_port, quiet_platform_config, wait_until

from platformd.app import PlatformDaemon
from stationd.console.hub import start_in
from stationd.daemon import StationDaemon
from stationd.video_feed import AccessUnit, FanOut, Viewer, decode_header

Factory = Callable[..., Awaitable[PlatformDaemon]]


def unit(key: bool, *, gap: bool = False, size: int = 10) -> AccessUnit:
    return AccessUnit(b"\x00" * size, key, 1000.0, 1001.0, after_gap=gap)


def drain(viewer: Viewer) -> list[dict[str, Any]]:
    out = [decode_header(m) for m in viewer.queue]
    viewer.queue.clear()
    viewer.allowance = 0
    return out


def test_a_new_viewer_gets_the_current_gop_replayed() -> None:
    fanout = FanOut()
    for key in (True, False, False, True, False):
        fanout.feed(unit(key))
    viewer = Viewer(feed=7)
    fanout.add(viewer)
    replay = drain(viewer)
    assert [(m["keyframe"], m["replayed"], m["feed"]) for m in replay] == [
        (True, True, 7),
        (False, True, 7),
    ]
    fanout.feed(unit(False))
    live = drain(viewer)
    assert [(m["seq"], m["replayed"]) for m in live] == [(6, False)]


def test_nothing_before_the_first_keyframe_and_a_gap_freezes_until_the_next() -> None:
    fanout = FanOut()
    viewer = Viewer(feed=1)
    fanout.add(viewer)
    fanout.feed(unit(False))  # joined mid-GOP: not decodable
    assert drain(viewer) == []
    fanout.feed(unit(True))
    fanout.feed(unit(False))
    fanout.feed(unit(False, gap=True))  # lost packets before this one
    fanout.feed(unit(False))
    assert [m["keyframe"] for m in drain(viewer)] == [True, False]
    fanout.feed(unit(True))
    assert [m["keyframe"] for m in drain(viewer)] == [True]
    assert fanout.gaps == 1
    assert fanout.held == 3


def test_a_viewer_that_falls_behind_skips_to_the_next_keyframe() -> None:
    fanout = FanOut()
    slow, fast = Viewer(feed=1, limit=3), Viewer(feed=1, limit=3)
    fanout.feed(unit(True))
    fanout.add(slow)
    fanout.add(fast)
    drain(fast)
    for _ in range(6):
        fanout.feed(unit(False))
        drain(fast)  # keeps up
    # slow: replayed key (allowance 1) + 3 live fit; the 4th live unit overflows.
    assert slow.cutbacks == 1
    assert slow.waiting_for_key
    assert len(slow.queue) == 0
    fanout.feed(unit(True))
    fanout.feed(unit(False))
    assert [m["keyframe"] for m in drain(slow)] == [True, False]
    assert fast.cutbacks == 0
    assert fast.skipped == 0


async def test_access_units_reach_a_websocket_viewer_with_capture_times(
    station: StationDaemon,
    platform_factory: Factory,
    fleet_key: bytes,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setattr("stationd.console.media.FEED_LINGER_S", 0.5)
    platform = await platform_factory(
        quiet_platform_config("platform.id=feed-rover", "sim.enabled=true", "navcam.enabled=true"),
        fleet_key,
    )
    api = f"http://127.0.0.1:{station.api_port}/api/rpc/ws"
    ids = iter(range(1, 1000))

    async with aiohttp.ClientSession() as http, http.ws_connect(api) as ws:

        async def call(method: str, **params: Any) -> Any:
            number = next(ids)
            await ws.send_str(
                json.dumps({"jsonrpc": "2.0", "id": number, "method": method, "params": params})
            )
            while True:
                message = await ws.receive(timeout=10)
                if message.type is not aiohttp.WSMsgType.TEXT:
                    continue
                answer = json.loads(message.data)
                if answer.get("id") == number:
                    assert "error" not in answer, answer
                    return answer["result"]

        hello = await call("console_subscribe")
        assert hello["session"] >= 1
        await call("connect", platform_id="feed-rover", url=platform.ctx.signaling_url)
        watching = await call("video_watch", platform_id="feed-rover")
        assert watching["watching"] == "feed-rover"
        frames: list[dict[str, Any]] = []
        pushed: set[str] = set()
        async with asyncio.timeout(15):
            while len(frames) < 8:
                message = await ws.receive()
                if message.type is aiohttp.WSMsgType.BINARY:
                    frames.append(decode_header(message.data))
                    assert message.data[24:28] == b"\x00\x00\x00\x01"  # Annex B start code
                elif message.type is aiohttp.WSMsgType.TEXT:
                    pushed.add(json.loads(message.data).get("method", ""))
        assert frames[0]["keyframe"], "the first frame a viewer gets is a keyframe"
        assert all(f["feed"] == watching["feed"] for f in frames)
        seqs = [f["seq"] for f in frames]
        assert seqs == sorted(seqs)
        assert len(set(seqs)) == len(seqs)
        # The platform stamped every frame; on loopback one clock: a few ms old on arrival.
        for f in frames:
            assert f["capture_ms"] > 0
            assert -5 < f["arrival_ms"] - f["capture_ms"] < 2000
        assert {"platforms", "connections"} <= pushed
        feeds = await call("video_feeds")
        assert feeds[0]["viewers"] == 1
        assert feeds[0]["units"] >= 8

        # Nobody watches: the feed lingers, then stops, and so does the platform's NavCam.
        media = platform.ctx.media
        assert media is not None
        navcam = media.nav_camera
        assert await call("video_unwatch") is True
        await wait_until(lambda: navcam()["state"] == "idle", timeout=10)
        assert await call("video_feeds") == []

        # Unless someone else took the stream meanwhile (a platform stream has one
        # destination): then it is left playing for them.
        await call("video_watch", platform_id="feed-rover")
        await call("stream_start", platform_id="feed-rover", stream="navcam", port=free_udp_port())
        await call("video_unwatch")
        async with asyncio.timeout(10):
            while await call("video_feeds"):
                await asyncio.sleep(0.2)
        assert navcam()["state"] == "playing"


async def test_the_page_worker_s_own_socket_carries_the_navcam_once_it_proves_the_token(
    station: StationDaemon,
    platform_factory: Factory,
    fleet_key: bytes,
) -> None:
    """The page's video worker opens a socket of its own (``console_media``): the NavCam's
    access units go there, from a keyframe, and no longer to the page's socket; a wrong token
    is refused; when the worker's socket closes the page's socket carries them again."""
    platform = await platform_factory(
        quiet_platform_config("platform.id=media-rover", "sim.enabled=true", "navcam.enabled=true"),
        fleet_key,
    )
    api = f"http://127.0.0.1:{station.api_port}/api/rpc/ws"
    async with aiohttp.ClientSession() as http, http.ws_connect(api) as page:
        hello = await _call(page, "console_subscribe")
        await _call(page, "connect", platform_id="media-rover", url=platform.ctx.signaling_url)
        watching = await _call(page, "video_watch", platform_id="media-rover")
        assert (await _frames(page, 3))[0]["feed"] == watching["feed"]

        async with http.ws_connect(api) as worker:
            refused = await _call(
                worker, "console_media", session=hello["session"], token="not-the-token"
            )
            assert refused["error"]["message"].startswith("no such console session")
            answer = await _call(
                worker, "console_media", session=hello["session"], token=hello["media_token"]
            )
            assert answer["result"] is True
            frames = await _frames(worker, 8)
            assert frames[0]["keyframe"]
            assert frames[0]["feed"] == watching["feed"]
            live = [f["seq"] for f in frames if not f["replayed"]]
            assert live, "live frames follow the GOP"
            # The page's socket gets none of them: only what was sent before the switch.
            late = await _frames(page, 100, within=1.0)
            assert all(f["seq"] < live[0] for f in late), (late, live)
        # The worker's socket closed: the page's own carries the NavCam again.
        assert len(await _frames(page, 3)) == 3


async def _call(ws: aiohttp.ClientWebSocketResponse, method: str, **params: Any) -> Any:
    """A JSON-RPC call on ``ws``: its whole answer (result or error)."""
    await ws.send_str(json.dumps({"jsonrpc": "2.0", "id": 7, "method": method, "params": params}))
    while True:
        message = await ws.receive(timeout=10)
        if message.type is aiohttp.WSMsgType.TEXT and json.loads(message.data).get("id") == 7:
            answer: dict[str, Any] = json.loads(message.data)
            return answer if method == "console_media" else answer["result"]


async def _frames(
    ws: aiohttp.ClientWebSocketResponse, count: int, within: float = 15.0
) -> list[dict[str, Any]]:
    """Up to ``count`` NavCam frames arriving on ``ws`` within ``within`` s (pushes skipped)."""
    frames: list[dict[str, Any]] = []
    with contextlib.suppress(TimeoutError):
        async with asyncio.timeout(within):
            while len(frames) < count:
                message = await ws.receive()
                if message.type is aiohttp.WSMsgType.BINARY:
                    frames.append(decode_header(message.data))
    return frames


async def test_work_for_a_stopping_hub_is_closed_not_left_unawaited() -> None:
    """A page closing while the console hub stops: its media socket's close goes nowhere (the
    server closes it), without raising from the page's handler or a never-awaited coroutine."""
    started: list[str] = []

    async def close_socket() -> None:
        started.append("closed")

    async def stop_hub(group: asyncio.TaskGroup) -> None:
        raise RuntimeError("the hub stops")

    with pytest.raises(ExceptionGroup):
        async with asyncio.TaskGroup() as group:
            group.create_task(stop_hub(group))
            await asyncio.sleep(1)  # cancelled: the group aborts
    work = close_socket()
    with warnings.catch_warnings(record=True) as warned:
        warnings.simplefilter("always")  # a never-awaited coroutine warns when collected
        assert not start_in(group, work, "console:1:media")
        assert not start_in(None, close_socket(), "console:1:media")
        gc.collect()
    assert [str(w.message) for w in warned] == []
    assert work.cr_frame is None  # closed, not pending
    assert started == []
    async with asyncio.TaskGroup() as group:
        assert start_in(group, close_socket(), "console:1:media")
    assert started == ["closed"]
