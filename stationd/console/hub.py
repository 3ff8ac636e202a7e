"""The console hub: the pages' sessions, their pushes, the notifications kept for them."""

from __future__ import annotations

import asyncio
import collections
import contextlib
import itertools
import json
import logging
import time
from collections.abc import Coroutine
from typing import Any

from aiohttp import web

from brasidas import topics
from brasidas.actor import Actor, wait_forever
from brasidas.codecs.jsonrpc import INVALID_PARAMS, CallContext, RpcError
from brasidas.media.pipeline import PipelineStream
from brasidas.messages import PlatformLink, StationNotification
from stationd.console.drive import ConsoleDrive
from stationd.console.media import ConsoleMedia
from stationd.console.session import (
    NOTES_KEPT,
    NOTES_QUEUED_MAX,
    PUSH_PERIOD_S,
    SEND_TIMEOUT_S,
    TELEMETRY_CHECK_S,
    ConsoleSession,
)
from stationd.context import StationContext
from stationd.video_feed import Feed

_LOGGER = logging.getLogger(__name__)


def start_in(group: asyncio.TaskGroup | None, work: Coroutine[Any, Any, Any], name: str) -> bool:
    """``work`` as a task of ``group``; False, and ``work`` closed unstarted, when the group
    takes no more (the hub is stopping, and its stop does that work: the pipelines stopped,
    the server closing its sockets). A page closing just then raised from its handler and
    left a "never awaited" coroutine behind."""
    try:
        if group is None:
            raise RuntimeError("no group")
        group.create_task(work, name=name)
    except RuntimeError:
        work.close()
        return False
    return True


class ConsoleHub(ConsoleMedia, ConsoleDrive, Actor):
    """Console sessions, per-platform NavCam feeds, and the console drive watchdog."""

    name = "console"

    def __init__(self, ctx: StationContext) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self.sessions: dict[int, ConsoleSession] = {}
        self.feeds: dict[tuple[str, str], Feed] = {}
        """By (platform id, stream): the NavCam and the microphone, each received once."""
        self.drivers: dict[str, int] = {}
        """Platform id → the console session that engaged its override (and may drive it)."""
        self._numbers = itertools.count(1)
        self._feed_numbers = itertools.count(1)
        self._unwatched_since: dict[tuple[str, str], float] = {}
        self._feed_lock = asyncio.Lock()
        self.dropped_binary = 0
        """Binary messages from pages that were not push-to-talk audio while talking."""
        self.notes_kept: collections.deque[dict[str, Any]] = collections.deque(maxlen=NOTES_KEPT)
        self.page_latency: dict[str, tuple[float, float]] = {}
        """Platform id → the latest glass-to-glass p95 (ms) a page measured, and when."""
        self._destinations: dict[tuple[str, str], tuple[float, list[str] | None]] = {}
        """(platform, stream) → when the platform's destinations were last asked, and them."""
        self._group: asyncio.TaskGroup | None = None

    async def run(self) -> None:
        self.subscribe(topics.STATION_NOTIFICATIONS, self._on_notification)
        self.subscribe(topics.PLATFORM_CONNECTED, lambda _c: self._mark_dirty())
        self.subscribe(topics.PLATFORM_DISCONNECTED, self._on_disconnected)
        self.subscribe(topics.PLATFORM_DISCOVERED, lambda _s: self._mark_dirty())
        self.subscribe(topics.PLATFORM_LOST, lambda _s: self._mark_dirty())
        try:
            async with asyncio.TaskGroup() as group:
                self._group = group
                group.create_task(self._reap_feeds(), name="console:feeds")
                await wait_forever()
        finally:
            self._group = None

    async def async_stop(self) -> None:
        pipelines: list[PipelineStream] = [f.depayloader for f in self.feeds.values()]
        pipelines += [s.talk for s in self.sessions.values() if s.talk is not None]
        self.feeds.clear()
        await asyncio.gather(*(p.stop() for p in pipelines), return_exceptions=True)

    # ------------------------------------------------------------------ bus

    def _on_notification(self, note: StationNotification) -> None:
        self.notes_kept.append(note.as_dict())
        for session in self.sessions.values():
            if len(session.notes) < NOTES_QUEUED_MAX:  # a stalled page gets no more
                session.notes.append(note.as_dict())
            session.dirty.set()

    def _on_disconnected(self, link: PlatformLink) -> None:
        platform_id = link.platform_id
        self.drivers.pop(platform_id, None)
        for key in [key for key in self.feeds if key[0] == platform_id]:
            feed = self.feeds.pop(key)
            for session in self.sessions.values():
                for kind, watch in list(session.watches.items()):
                    if watch.feed is feed:
                        self._unwatch(session, kind)
            start_in(self._group, feed.depayloader.stop(), f"console:stop:{key}")
        for session in self.sessions.values():
            if session.talk_platform == platform_id:
                self._stop_talk(session)
        self._mark_dirty()

    # ------------------------------------------------------------------ sessions

    async def api_console_subscribe(self, call: CallContext) -> dict[str, Any]:
        """Start the pushes on this WebSocket; answers the session number and station time."""
        ws = call.extra.get("ws")
        if not isinstance(ws, web.WebSocketResponse) or self._group is None:
            raise RpcError(INVALID_PARAMS, "console_subscribe needs the WebSocket transport")
        existing = call.extra.get("console")
        if isinstance(existing, ConsoleSession):
            existing.dirty.set()
            return self._hello(existing)
        session = ConsoleSession(next(self._numbers), ws)
        session.notes.extend({**note, "replayed": True} for note in self.notes_kept)
        call.extra["console"] = session
        call.extra.setdefault("on_close", []).append(lambda: self._close(session))
        call.extra["on_binary"] = lambda data: self._on_binary(session, data)
        self.sessions[session.number] = session
        self._spawn(session, self._push(session), f"console:{session.number}:push")
        session.dirty.set()
        return self._hello(session)

    def _hello(self, session: ConsoleSession) -> dict[str, Any]:
        return {
            "session": session.number,
            "station_id": self.ctx.config.station.id,
            "time_ms": time.time_ns() / 1e6,
            "drive_timeout_s": self.ctx.config.console.drive_timeout,
            "media_token": session.media_token,
        }

    def api_console_focus(self, call: CallContext, platform_id: str) -> bool:
        """The platform this page shows: its telemetry is pushed as it arrives, the others'
        once a second. (``video_watch`` sets it too.)"""
        session = self._session(call)
        session.focus = platform_id
        session.dirty.set()
        return True

    def api_station_time(self, call: CallContext) -> float:
        """The station's wall clock (Unix ms): the page estimates its clock offset with it."""
        return time.time_ns() / 1e6

    def _close(self, session: ConsoleSession) -> None:
        """The page's socket closed: stop what it drove at once, drop its tasks."""
        session.closed = True
        self.sessions.pop(session.number, None)
        for kind in list(session.watches):
            self._unwatch(session, kind)
        self._stop_talk(session)
        driven = {p for p, number in self.drivers.items() if number == session.number}
        for platform_id in driven | set(session.drive_stops):
            self._stop_driving(session, platform_id)
        for platform_id in driven:
            self._release_when_gone(session, platform_id)
        for task in list(session.tasks):
            task.cancel("console closed")
        if session.media_ws is not None:
            # The page's video worker's socket goes with the page's own.
            start_in(self._group, session.media_ws.close(), f"console:{session.number}:media")
            session.media_ws = None

    async def _send(self, session: ConsoleSession, method: str, params: Any) -> None:
        text = json.dumps({"jsonrpc": "2.0", "method": method, "params": params}, allow_nan=False)
        try:
            async with asyncio.timeout(SEND_TIMEOUT_S):
                await session.ws.send_str(text)
        except TimeoutError:
            _LOGGER.warning("console %d stalled: closing its socket", session.number)
            await session.ws.close()
            raise ConnectionError("console socket stalled") from None

    async def _push(self, session: ConsoleSession) -> None:
        api = self.ctx.api
        last_full = 0.0
        try:
            while not session.ws.closed:
                now = time.monotonic()
                full = session.dirty.is_set() or now - last_full >= PUSH_PERIOD_S
                session.dirty.clear()
                if full:
                    last_full = now
                    await self._send(session, "platforms", await api.call_local("list_platforms"))
                    await self._send(session, "connections", self._connections(session))
                notes, session.notes = session.notes, []
                for note in notes:
                    await self._send(session, "notification", note)
                for platform_id in list(self.ctx.connections):
                    if not full and platform_id != session.focus:
                        continue  # the platforms it does not show: once a second (the map)
                    with contextlib.suppress(RpcError):
                        report = await api.call_local("get_telemetry", platform_id=platform_id)
                        stamp = report.get("platform_time")
                        if full or stamp != session.telemetry_seen.get(platform_id):
                            session.telemetry_seen[platform_id] = stamp
                            report["received_ms"] = time.time_ns() / 1e6
                            await self._send(session, "telemetry", report)
                if "video" in session.watches and full:
                    state = self._video_state(session)
                    state["reason"] = await self._video_reason(session)
                    await self._send(session, "video", state)
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(TELEMETRY_CHECK_S):
                        await session.dirty.wait()
        except (ConnectionError, RuntimeError) as err:
            _LOGGER.debug("console %d: push ended: %s", session.number, err)

    def _connections(self, session: ConsoleSession) -> list[dict[str, Any]]:
        answer = []
        for platform_id, connection in self.ctx.connections.items():
            summary = connection.summary()
            summary.pop("parameters", None)
            summary.pop("capabilities", None)
            driver = self.drivers.get(platform_id)
            summary["driver_session"] = driver
            summary["this_console_drives"] = driver == session.number
            answer.append(summary)
        return answer


async def async_setup(ctx: StationContext) -> None:
    hub = ConsoleHub(ctx)
    for name in (
        "console_subscribe",
        "console_media",
        "console_focus",
        "station_time",
        "video_watch",
        "video_unwatch",
        "video_feeds",
        "audio_listen",
        "audio_talk",
        "console_stream",
        "console_override",
        "console_drive",
        "console_latency",
    ):
        ctx.api.add(name, getattr(hub, f"api_{name}"), session_required=False)
    ctx.video_feeds = hub
    ctx.supervisor.start(hub)
