"""The browser console's side of the station: pushes, video, and the console's drive feed.

A page opens the local API's WebSocket (``/api/rpc/ws``, the same JSON-RPC the CLI uses) and
calls ``console_subscribe``: from then on the station pushes JSON-RPC notifications on that
socket — ``platforms`` (the beacons heard), ``connections`` (sessions, override, who drives),
``telemetry`` (one platform's report, as each snapshot arrives) and ``notification`` (group 90
warnings raised and cleared) — and, after ``video_watch``, the NavCam's access units as binary
messages (:mod:`stationd.video_feed`). Nothing is polled by the page.

The console's drive feed (``console_drive``) is for the page that engaged the override through
``console_override``: each call sets the velocity for ``console.drive_timeout`` (0.2 s) only,
so a page that stops sending — a closed or hidden tab, a stalled socket, a crashed script —
stops the robot here, whatever its JavaScript did; a closed socket stops it at once.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from aiohttp import web

from brasidas import topics
from brasidas.actor import Actor, wait_forever
from brasidas.codecs.jsonrpc import INVALID_PARAMS, CallContext, RpcError
from brasidas.media.pipeline import PipelineStream, StreamState
from brasidas.messages import PlatformLink, StationNotification
from stationd.context import StationContext
from stationd.media import free_udp_port, receive_host
from stationd.teleop import STOP
from stationd.video_feed import FRAME_TYPE_TALK, HEADER, Feed, OpusSender, Viewer, pump

_LOGGER = logging.getLogger(__name__)

NOT_DRIVING = -32011
PUSH_PERIOD_S = 1.0
"""Platforms, connections and link figures are pushed at least this often (ages, silence)."""
TELEMETRY_CHECK_S = 0.1
"""How often a new telemetry snapshot is looked for (the platform sends 5 per second)."""
FEED_LINGER_S = 10.0
"""A feed nobody watches is stopped after this long (switching back is instant meanwhile)."""
NOTES_QUEUED_MAX = 200
"""Notifications waiting for one page at most (its socket stalled)."""
SEND_TIMEOUT_S = 5.0
"""A push that cannot be written for this long closes the socket (the page reconnects)."""


@dataclass(eq=False)
class Watch:
    """One feed a page receives: its viewer and the task sending to the page."""

    feed: Feed
    viewer: Viewer
    remove: Callable[[], None]
    task: asyncio.Task[None]


@dataclass(eq=False)
class ConsoleSession:
    """One page: its socket, what it watches and listens to, and whether it drives."""

    number: int
    ws: web.WebSocketResponse
    tasks: set[asyncio.Task[None]] = field(default_factory=set)
    watches: dict[str, Watch] = field(default_factory=dict)
    """By kind: "video" (one NavCam at a time) and "audio" (one microphone)."""
    talk: OpusSender | None = None
    talk_platform: str = ""
    dirty: asyncio.Event = field(default_factory=asyncio.Event)
    notes: list[dict[str, Any]] = field(default_factory=list)
    telemetry_seen: dict[str, Any] = field(default_factory=dict)
    focus: str = ""
    """The platform the page shows (its NavCam): its telemetry is pushed as it arrives."""
    drive_stops: dict[str, asyncio.TimerHandle] = field(default_factory=dict)
    """By platform id: when this page's last drive input lapses."""
    closed: bool = False


class ConsoleHub(Actor):
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

    def _mark_dirty(self) -> None:
        for session in self.sessions.values():
            session.dirty.set()

    def _on_notification(self, note: StationNotification) -> None:
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
            if self._group is not None:
                self._group.create_task(feed.depayloader.stop(), name=f"console:stop:{key}")
        for session in self.sessions.values():
            if session.talk_platform == platform_id:
                self._stop_talk(session)
        self._mark_dirty()

    # ------------------------------------------------------------------ sessions

    def _session(self, call: CallContext) -> ConsoleSession:
        session = call.extra.get("console")
        if not isinstance(session, ConsoleSession):
            raise RpcError(INVALID_PARAMS, "call console_subscribe first (on the WebSocket)")
        return session

    def _spawn(self, session: ConsoleSession, coro: Any, name: str) -> asyncio.Task[None]:
        assert self._group is not None
        task = self._group.create_task(coro, name=name)
        session.tasks.add(task)
        task.add_done_callback(session.tasks.discard)
        return task

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
        for task in list(session.tasks):
            task.cancel("console closed")

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
                    await self._send(session, "video", self._video_state(session))
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

    async def _pump(self, session: ConsoleSession, viewer: Viewer) -> None:
        with contextlib.suppress(ConnectionError, RuntimeError):
            await pump(viewer, session.ws.send_bytes)

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
                await connection.call("start_stream", name=stream, port=feed.port)
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
        """Stop the platform's stream unless someone else (``brasidas-station view``) took it:
        a platform stream has one destination."""
        connection = self.ctx.connections.get(feed.platform_id)
        if connection is None:
            return
        for stream in await connection.call("list_streams"):
            if stream.get("name") == feed.stream:
                if str(stream.get("destination", "")).endswith(f":{feed.port}"):
                    await connection.call("stop_stream", name=feed.stream)
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

    # ------------------------------------------------------------------ override and drive

    async def api_console_override(
        self, call: CallContext, platform_id: str, engaged: bool, force: bool = False
    ) -> dict[str, Any]:
        """Engage or release the manual override; the page that engaged it is the one driving.
        ``force`` takes control from another station (``movrd --force``)."""
        session = self._session(call)
        answer: dict[str, Any] = await self.ctx.api.call_local(
            "movrd", platform_id=platform_id, engaged=engaged, force=force
        )
        if answer.get("accepted"):
            if engaged:
                self.drivers[platform_id] = session.number
            else:
                self._stop_driving(session, platform_id)
                self.drivers.pop(platform_id, None)
        self._mark_dirty()
        return answer

    async def api_console_drive(
        self, call: CallContext, platform_id: str, linear: float, angular: float
    ) -> dict[str, Any]:
        """This page's velocity for the next ``console.drive_timeout`` seconds."""
        session = self._session(call)
        if self.drivers.get(platform_id) != session.number:
            raise RpcError(NOT_DRIVING, f"this console does not hold {platform_id}'s override")
        answer: dict[str, Any] = await self.ctx.api.call_local(
            "teleop_set", platform_id=platform_id, linear=linear, angular=angular
        )
        if session.closed:  # the page went away meanwhile
            self._stop_driving(session, platform_id)
            return answer
        stop = session.drive_stops.pop(platform_id, None)
        if stop is not None:
            stop.cancel()
        session.drive_stops[platform_id] = asyncio.get_running_loop().call_later(
            self.ctx.config.console.drive_timeout, self._stop_driving, session, platform_id
        )
        return answer

    def _stop_driving(self, session: ConsoleSession, platform_id: str) -> None:
        """Zero the drive input at once (the sender streams zeros from its next tick)."""
        stop = session.drive_stops.pop(platform_id, None)
        if stop is not None:
            stop.cancel()
        if self.ctx.teleop is not None:
            self.ctx.teleop.set_drive(platform_id, STOP)


async def async_setup(ctx: StationContext) -> None:
    hub = ConsoleHub(ctx)
    for name in (
        "console_subscribe",
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
    ):
        ctx.api.add(name, getattr(hub, f"api_{name}"), session_required=False)
    ctx.video_feeds = hub
    ctx.supervisor.start(hub)
