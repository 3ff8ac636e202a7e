"""A console page's session and what the hub's parts share."""

from __future__ import annotations

import asyncio
import collections
import secrets
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from aiohttp import web

from brasidas.codecs.jsonrpc import INVALID_PARAMS, CallContext, RpcError
from stationd.context import StationContext
from stationd.video_feed import Feed, OpusSender, Viewer

PUSH_PERIOD_S = 1.0
"""Platforms, connections and link figures are pushed at least this often (ages, silence)."""
TELEMETRY_CHECK_S = 0.1
"""How often a new telemetry snapshot is looked for (the platform sends 5 per second)."""
NOTES_QUEUED_MAX = 200
"""Notifications waiting for one page at most (its socket stalled)."""
SEND_TIMEOUT_S = 5.0
"""A push that cannot be written for this long closes the socket (the page reconnects)."""
NOTES_KEPT = 100
"""Notifications the station keeps for pages that open later (a reload shows them)."""


@dataclass(eq=False)
class Watch:
    """One feed a page receives: its viewer and the task sending to the page."""

    feed: Feed
    viewer: Viewer
    remove: Callable[[], None]
    task: asyncio.Task[None]
    units_seen: int = -1
    """The feed's access-unit count when last looked at, and when it last moved."""
    units_moved_at: float = 0.0


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
    media_ws: web.WebSocketResponse | None = None
    """The page's video worker's own socket, once it proved ``media_token``: the NavCam's
    access units go there, past the page's main thread (busy with layout and paint)."""
    media_token: str = field(default_factory=lambda: secrets.token_urlsafe(18))


class ConsoleParts:
    """What the hub's parts (media, drive) share: the station, the pages, the task group."""

    ctx: StationContext
    sessions: dict[int, ConsoleSession]
    feeds: dict[tuple[str, str], Feed]
    drivers: dict[str, int]
    notes_kept: collections.deque[dict[str, Any]]
    _group: asyncio.TaskGroup | None

    def _mark_dirty(self) -> None:
        for session in self.sessions.values():
            session.dirty.set()

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
