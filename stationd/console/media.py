"""The console's NavCam and microphone feeds (each received once, fanned out to the pages),
why a watched feed is silent, the pages' glass-to-glass for the speed cap, push-to-talk."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import math
import secrets
import time
from collections.abc import Callable
from typing import Any

from aiohttp import web

from brasidas.codecs.jsonrpc import INVALID_PARAMS, CallContext, RpcError
from brasidas.media.pipeline import StreamState
from stationd.console.session import ConsoleParts, ConsoleSession, Watch
from stationd.media import free_udp_port, receive_host
from stationd.video_feed import (
    FRAME_TYPE_TALK,
    FRAME_TYPE_VIDEO,
    HEADER,
    Feed,
    OpusSender,
    Viewer,
    pump,
)

_LOGGER = logging.getLogger(__name__)

FEED_LINGER_S = 10.0
"""A feed nobody watches is stopped after this long (switching back is instant meanwhile)."""
PAGE_LATENCY_MAX_AGE_S = 1.5
"""A page's glass-to-glass report is used this long (it reports once a second, of the last
second): a page that stops reporting stops counting, and the platform's assumption returns."""
DESTINATIONS_ASKED_EVERY_S = 2.0
DESTINATIONS_WAIT_S = 0.5
VIDEO_SILENT_S = 1.0
"""A watched feed with no access unit for this long gets a reason (paused, stopped, elsewhere)."""


class ConsoleMedia(ConsoleParts):
    """The hub's feeds: video and audio to the pages, push-to-talk from them."""

    page_latency: dict[str, tuple[float, float]]
    """Platform id → the latest glass-to-glass p95 (ms) a page measured, and when."""
    dropped_binary: int
    _feed_numbers: itertools.count[int]
    _unwatched_since: dict[tuple[str, str], float]
    _feed_lock: asyncio.Lock
    _destinations: dict[tuple[str, str], tuple[float, list[str] | None]]

    # ------------------------------------------------------------------ video and audio

    async def api_video_watch(
        self, call: CallContext, platform_id: str, stream: str = "navcam"
    ) -> dict[str, Any]:
        """Send ``platform_id``'s NavCam to this page (its current GOP first); one at a time."""
        session = self._session(call)
        session.focus = platform_id
        await self._watch(session, "video", platform_id, stream)
        return self._video_state(session)

    def api_video_unwatch(self, call: CallContext) -> bool:
        return self._unwatch(self._session(call), "video")

    async def api_audio_listen(
        self, call: CallContext, platform_id: str, on: bool = True, stream: str = "audio_out"
    ) -> dict[str, Any]:
        """The platform's microphone to this page as Opus packets (decoded there), or stop."""
        session = self._session(call)
        if not on:
            self._unwatch(session, "audio")
            return {"listening": None}
        watch = await self._watch(session, "audio", platform_id, stream)
        return {"listening": platform_id, **watch.feed.describe()}

    def api_video_feeds(self, call: CallContext) -> list[dict[str, Any]]:
        """Every feed: its pipeline, fan-out counters and viewers."""
        return [feed.describe() for feed in self.feeds.values()]

    async def _watch(
        self, session: ConsoleSession, kind: str, platform_id: str, stream: str
    ) -> Watch:
        feed = await self._feed(platform_id, stream, audio=kind == "audio")
        watch = session.watches.get(kind)
        if watch is None or watch.feed is not feed:
            self._unwatch(session, kind)
            viewer = feed.viewer()
            task = self._spawn(
                session, self._pump(session, viewer), f"console:{session.number}:{kind}"
            )
            watch = Watch(feed, viewer, feed.fanout.add(viewer), task)
            session.watches[kind] = watch
        self._unwatched_since.pop((platform_id, stream), None)
        return watch

    def api_console_media(self, call: CallContext, session: int, token: str) -> bool:
        """This WebSocket (the page's video worker's own) carries session ``session``'s NavCam
        from now on, its current GOP first: the access units no longer wait for the page's
        main thread. ``token`` is the ``media_token`` ``console_subscribe`` answered."""
        ws = call.extra.get("ws")
        if not isinstance(ws, web.WebSocketResponse):
            raise RpcError(INVALID_PARAMS, "console_media needs the WebSocket transport")
        owner = self.sessions.get(session)
        if owner is None or not secrets.compare_digest(owner.media_token, token):
            raise RpcError(INVALID_PARAMS, "no such console session (or the wrong token)")
        owner.media_ws = ws
        call.extra.setdefault("on_close", []).append(lambda: self._media_closed(owner, ws))
        watch = owner.watches.get("video")
        if watch is not None:  # what was queued for the other socket: from a keyframe again
            watch.feed.fanout.rewind(watch.viewer)
        return True

    def _media_closed(self, session: ConsoleSession, ws: web.WebSocketResponse) -> None:
        if session.media_ws is ws:
            session.media_ws = None

    async def _pump(self, session: ConsoleSession, viewer: Viewer) -> None:
        async def send(message: bytes) -> None:
            media = session.media_ws if viewer.kind == FRAME_TYPE_VIDEO else None
            if media is not None and not media.closed:
                try:
                    await media.send_bytes(message)
                    return
                except ConnectionError:
                    self._media_closed(session, media)
            await session.ws.send_bytes(message)

        with contextlib.suppress(ConnectionError, RuntimeError):
            await pump(viewer, send)

    def _unwatch(self, session: ConsoleSession, kind: str) -> bool:
        watch = session.watches.pop(kind, None)
        if watch is None:
            return False
        watch.remove()
        watch.task.cancel("unwatched")
        if not watch.feed.fanout.viewers:
            self._unwatched_since[(watch.feed.platform_id, watch.feed.stream)] = time.monotonic()
        return True

    def _video_state(self, session: ConsoleSession) -> dict[str, Any]:
        watch = session.watches.get("video")
        if watch is None:
            return {"watching": None}
        return {
            "watching": watch.feed.platform_id,
            **watch.feed.describe(),
            "viewer": watch.viewer.stats(),
        }

    async def _video_reason(self, session: ConsoleSession) -> str:
        """Why the watched feed brings nothing, when it does not ("" while units arrive): the
        platform paused or stopped the stream, it failed, or it is sent elsewhere."""
        watch = session.watches.get("video")
        if watch is None:
            return ""
        now = time.monotonic()
        # Units held back after a loss (waiting for a keyframe) show nothing: not movement.
        units = watch.feed.fanout.units - watch.feed.fanout.held
        if units != watch.units_seen:
            watch.units_seen, watch.units_moved_at = units, now
        if now - watch.units_moved_at < VIDEO_SILENT_S:
            return ""
        feed = watch.feed
        with contextlib.suppress(RpcError):
            report = await self.ctx.api.call_local("get_telemetry", platform_id=feed.platform_id)
            states = ((report.get("snapshot") or {}).get("streams") or {}).get("states") or {}
            state = str(states.get(feed.stream, ""))
            if state == "paused":
                return f"{feed.stream} paused on the platform"
            if state in ("idle", "stopped"):
                return f"{feed.stream} stopped on the platform"
            if state in ("failed", "error"):
                return f"{feed.stream} failed on the platform"
        if feed.depayloader.state is StreamState.FAILED:
            return f"the station's receiver failed: {feed.depayloader.reason}"
        loss = feed.loss_reason()
        if loss:
            return loss
        destinations = await self._platform_destinations(feed)
        if destinations is not None and not any(d.endswith(f":{feed.port}") for d in destinations):
            elsewhere = ", ".join(destinations) or "nowhere"
            return f"{feed.stream} taken by another consumer (sent to {elsewhere})"
        return f"no {feed.stream} packets arrive from the platform"

    async def _platform_destinations(self, feed: Feed) -> list[str] | None:
        """Where the platform sends ``feed``'s stream, or None (unknown). Asked at most every
        2 s and waited for 0.5 s at most: a silent platform never holds up a page's pushes."""
        key = (feed.platform_id, feed.stream)
        asked = self._destinations.get(key)
        now = time.monotonic()
        if asked is not None and now - asked[0] < DESTINATIONS_ASKED_EVERY_S:
            return asked[1]
        self._destinations[key] = (now, None)
        connection = self.ctx.connections.get(feed.platform_id)
        if connection is None:
            return None
        try:
            async with asyncio.timeout(DESTINATIONS_WAIT_S):
                streams = await connection.call("list_streams")
        except (RpcError, ConnectionError, TimeoutError):
            return None
        for stream in streams:
            if stream.get("name") == feed.stream:
                found = [str(d) for d in stream.get("destinations") or []]
                if not found and stream.get("destination"):
                    found = [str(stream["destination"])]
                self._destinations[key] = (now, found)
                return found
        return None

    # ------------------------------------------------------------------ latency for the speed cap

    def api_console_latency(self, call: CallContext, platform_id: str, p95_ms: float) -> bool:
        """The page's glass-to-glass p95 of the last second for ``platform_id``'s NavCam: this
        station's heartbeats report it while it holds the override (the platform's speed cap),
        as ``brasidas-station view`` does with its own."""
        self._session(call)
        if (
            isinstance(p95_ms, bool)
            or not isinstance(p95_ms, int | float)
            or not math.isfinite(p95_ms)
            or not 0 <= p95_ms <= 60_000
        ):
            raise RpcError(INVALID_PARAMS, "invalid params: p95_ms must be 0-60000")
        self.page_latency[platform_id] = (float(p95_ms), time.monotonic())
        connection = self.ctx.connections.get(platform_id)
        if connection is not None and not isinstance(connection.video_latency, PageLatency):
            connection.video_latency = PageLatency(self, platform_id, connection.video_latency)
        return True

    async def open_feed(self, platform_id: str, stream: str = "navcam") -> Feed:
        """A platform's video feed, started if needed and shared with the pages watching it:
        another station subsystem (the Foxglove server) adds its own viewer to its fan-out."""
        return await self._feed(platform_id, stream, audio=False)

    def release_feed(self, platform_id: str, stream: str = "navcam") -> None:
        """A viewer added through :meth:`open_feed` left: with none left, the feed lingers
        and stops like a page's."""
        key = (platform_id, stream)
        feed = self.feeds.get(key)
        if feed is not None and not feed.fanout.viewers:
            self._unwatched_since.setdefault(key, time.monotonic())

    async def _feed(self, platform_id: str, stream: str, *, audio: bool) -> Feed:
        async with self._feed_lock:
            key = (platform_id, stream)
            feed = self.feeds.get(key)
            if feed is not None and feed.depayloader.state is not StreamState.IDLE:
                return feed
            connection = await self.ctx.connection(platform_id)
            host = receive_host(connection.platform_host)
            feed = Feed(
                platform_id,
                next(self._feed_numbers),
                host=host,
                port=free_udp_port(host),
                stream=stream,
                audio=audio,
            )
            state = await feed.depayloader.start()
            if state is StreamState.FAILED:
                await feed.depayloader.stop()
                raise RpcError(
                    INVALID_PARAMS, f"cannot receive {stream}: {feed.depayloader.reason}"
                )
            try:
                started = await connection.call("start_stream", name=stream, port=feed.port)
                if isinstance(started, dict) and isinstance(started.get("rtcp_port"), int):
                    feed.depayloader.set_feedback(connection.platform_host, started["rtcp_port"])
            except BaseException:
                await feed.depayloader.stop()
                raise
            self.feeds[key] = feed
            assert self._group is not None
            self._group.create_task(feed.depayloader.supervise(), name=f"console:feed:{key}")
            return feed

    # ------------------------------------------------------------------ push-to-talk

    async def api_audio_talk(
        self, call: CallContext, platform_id: str, on: bool = True
    ) -> dict[str, Any]:
        """Push-to-talk: this page's Opus packets (binary messages of type 3) to the platform's
        speaker while on; off stops the platform's speaker stream."""
        session = self._session(call)
        connection = await self.ctx.connection(platform_id)
        if not on:
            self._stop_talk(session)
            with contextlib.suppress(RpcError, ConnectionError, TimeoutError):
                await connection.call("stop_stream", name="audio_in")
            return {"talking": None}
        if session.talk is not None and session.talk_platform == platform_id:
            return {"talking": platform_id, **session.talk.describe()}
        self._stop_talk(session)
        listening: dict[str, Any] = await connection.call("start_stream", name="audio_in")
        host = str(listening.get("host") or "")
        if host in ("", "0.0.0.0", "::"):
            host = connection.platform_host
        sender = OpusSender(f"{platform_id}/talk", host=host, port=int(listening["port"]))
        if await sender.start() is StreamState.FAILED:
            await sender.stop()
            raise RpcError(INVALID_PARAMS, f"cannot send audio: {sender.reason}")
        session.talk, session.talk_platform = sender, platform_id
        return {"talking": platform_id, **sender.describe()}

    def _on_binary(self, session: ConsoleSession, data: bytes) -> None:
        """A binary message from the page: push-to-talk audio; anything else is dropped."""
        if len(data) <= HEADER.size or data[0] != FRAME_TYPE_TALK or session.talk is None:
            self.dropped_binary += 1
            return
        try:
            session.talk.push(data[HEADER.size :])
        except Exception:  # never the page's socket for one bad packet
            self.dropped_binary += 1
            _LOGGER.exception("console %d: push-to-talk packet refused", session.number)

    def _stop_talk(self, session: ConsoleSession) -> None:
        sender, session.talk, session.talk_platform = session.talk, None, ""
        if sender is not None and self._group is not None:
            self._group.create_task(sender.stop(), name=f"console:{session.number}:talk-stop")

    async def _reap_feeds(self) -> None:
        while True:
            await asyncio.sleep(1.0)
            now = time.monotonic()
            for key, since in list(self._unwatched_since.items()):
                feed = self.feeds.get(key)
                if feed is None or feed.fanout.viewers:
                    self._unwatched_since.pop(key, None)
                elif now - since > FEED_LINGER_S:
                    self._unwatched_since.pop(key, None)
                    self.feeds.pop(key, None)
                    await feed.depayloader.stop()
                    with contextlib.suppress(RpcError, ConnectionError, TimeoutError):
                        await self._stop_platform_stream(feed)

    async def _stop_platform_stream(self, feed: Feed) -> None:
        """Stop the console's copy of the platform's stream (the one sent to the feed's port);
        the copies of other consumers (``brasidas-station view``) go on."""
        connection = self.ctx.connections.get(feed.platform_id)
        if connection is None:
            return
        for stream in await connection.call("list_streams"):
            if stream.get("name") == feed.stream:
                sent_to = [str(d) for d in stream.get("destinations") or []]
                sent_to.append(str(stream.get("destination", "")))
                if any(d.endswith(f":{feed.port}") for d in sent_to):
                    await connection.call("stop_stream", name=feed.stream, port=feed.port)
                return

    async def api_console_stream(
        self, call: CallContext, platform_id: str, name: str, action: str
    ) -> dict[str, Any]:
        """Start, pause or stop one platform stream; a NavCam start goes to the console's feed."""
        if action not in ("start", "pause", "stop"):
            raise RpcError(INVALID_PARAMS, "invalid params: action must be start, pause or stop")
        connection = await self.ctx.connection(platform_id)
        params: dict[str, Any] = {"name": name}
        feed = self.feeds.get((platform_id, name))
        if action == "start" and feed is not None:
            params["port"] = feed.port
        answer: dict[str, Any] = await connection.call(f"{action}_stream", **params)
        return answer


class PageLatency:
    """A connection's video latency: the pages' fresh report, else what it had (``view``'s
    receiver)."""

    def __init__(
        self, hub: ConsoleMedia, platform_id: str, fallback: Callable[[], float | None] | None
    ) -> None:
        self.hub = hub
        self.platform_id = platform_id
        self.fallback = fallback

    def __call__(self) -> float | None:
        """The age of the picture on the page: its last glass-to-glass p95 plus how long the
        feed has been frozen since (issue 28: a frozen picture is latency, so the speed cap
        falls as the video fails), while the feed runs; else the fallback."""
        report = self.hub.page_latency.get(self.platform_id)
        feed = self.hub.feeds.get((self.platform_id, "navcam"))
        staleness = feed.fanout.staleness_ms(time.time() * 1000) if feed is not None else None
        if report is not None and staleness is not None:
            return report[0] + staleness
        if report is not None and time.monotonic() - report[1] <= PAGE_LATENCY_MAX_AGE_S:
            return report[0]
        return self.fallback() if self.fallback is not None else None
