"""Foxglove, live (issue 23): the station serves the Foxglove WebSocket protocol
(``foxglove-sdk``, subprotocol ``foxglove.sdk.v1``) on ``foxglove.host:port``.

Every connected platform gets the recorder's channels (:mod:`brasidas.recording.schemas`),
under the recordings' own names (``/gps``: one layout fits a live robot and its files) for the
first platform, and prefixed by its id (``/rover-2/gps``) for each other connected meanwhile
(or for all, ``foxglove.platform_prefix``): positions, every telemetry section, the motor
command and the velocity source it came from (the motion section), state changes (failsafe,
control, override, streams, patrol) from the station's telemetry link; the system commands
this station sends (``/commands``); the station's notifications as ``foxglove.Log``; the area
map and the planned route as ``foxglove.GeoJSON``; the lidar's scan (``/lidar/scan``, in 5°
sectors), fused pose (``/pose/fused``) and occupancy grid (``/grid``, fetched when its
revision moves); and the NavCam as
``foxglove.CompressedVideo`` while a client subscribes to it (the console's shared feed, no
re-encoding). ``/pose/local`` is not served: telemetry carries no local frame. Read-only: the
server advertises no client publishing, services or parameters; control goes through the
station's own authority.

The SDK runs its server on its own threads. Logging to a channel is safe from any thread;
its listener's callbacks (subscribe, unsubscribe) arrive on those threads and reach the
event loop only through ``loop.call_soon_threadsafe``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import time
from collections.abc import Callable
from typing import Any

import foxglove
from foxglove.websocket import ChannelView, Client, ServerListener

from brasidas import topics
from brasidas.actor import Actor
from brasidas.codecs.jsonrpc import RpcError
from brasidas.codecs.telemetry_schema import Autonomy, LidarView, Section, Snapshot
from brasidas.messages import CommandSent, PlatformLink, StationNotification, TelemetrySnapshot
from brasidas.perception.view import GridRefused, grid_from_json
from brasidas.recording import projection, schemas
from brasidas.recording.projection import StateChange
from brasidas.recording.schemas import ChannelSpec
from stationd.context import StationContext
from stationd.foxglove_guard import UPSTREAM_HOST, OriginGuard, guard_for
from stationd.video_feed import HEADER, Viewer, pump

_LOGGER = logging.getLogger(__name__)

REPUBLISH_NS = 1_000_000_000
"""An unchanged telemetry section (and what it feeds) is published again this often."""
PORT_OVERRIDE: int | None = None
"""Replaces ``foxglove.port`` when set: the test suite sets 0, so the many stations its tests
start never take the well-known port (nor collide on it)."""


class _Listener(ServerListener):
    """The SDK's server listener: called on its threads, forwards to the loop."""

    def __init__(self, loop: asyncio.AbstractEventLoop, owner: FoxgloveLive) -> None:
        self.loop = loop
        self.owner = owner

    def on_subscribe(self, client: Client, channel: ChannelView) -> None:
        self._forward(self.owner.subscribed, str(channel.topic), 1)

    def on_unsubscribe(self, client: Client, channel: ChannelView) -> None:
        self._forward(self.owner.subscribed, str(channel.topic), -1)

    def _forward(self, callback: Callable[[str, int], None], topic: str, delta: int) -> None:
        with contextlib.suppress(RuntimeError):  # the loop closed: nobody to tell
            self.loop.call_soon_threadsafe(callback, topic, delta)


FED_AT_ONCE = (
    schemas.NAVCAM,
    schemas.GPS,
    schemas.POSE,
    schemas.STATE,
    schemas.MAP,
    schemas.ROUTE,
    schemas.COMMANDS,
    schemas.TELEOP_VELOCITY,
    schemas.AUTONOMY_VELOCITY,
    schemas.MOTOR_COMMAND,
)
"""Advertised when a platform connects: what the station feeds from every platform."""


class _PlatformChannels:
    """One platform's channels and what was last published on them.

    The channels the station feeds are advertised at once (the NavCam's subscription is what
    fetches it); a telemetry section's and the log's with their first message, so a client is
    never offered a channel that nothing feeds (``/pose/local``: telemetry carries no local
    frame; ``/telemetry/turret`` on a platform without one)."""

    def __init__(self, platform_id: str, context: foxglove.Context, *, prefix: bool = True) -> None:
        self.platform_id = platform_id
        self.prefix = f"/{platform_id}" if prefix else ""
        """Before each topic: the platform id, or nothing (the recordings' names)."""
        self.context = context
        self.channels: dict[str, foxglove.Channel] = {}
        for spec in FED_AT_ONCE:
            self._channel(spec)
        self.pending: Snapshot | None = None
        """The newest snapshot from the station's telemetry, not yet projected."""
        self.previous: Snapshot | None = None
        """The snapshot projected last."""
        self.logged_at: dict[type[Section], int] = {}
        """When each telemetry section was last published (ns): re-published every
        :data:`REPUBLISH_NS` unchanged, so a client that subscribes later gets it too."""
        self.states: dict[str, StateChange] = {}
        self.map_rev: int | None = None
        self.grid_rev = 0
        self.grid_data: bytes | None = None
        """The occupancy grid last published: again to each new subscriber (a robot that
        stopped, or sees nothing to match, draws no new one)."""
        self.map_data: bytes | None = None
        """The area map last published: again to each new subscriber (it changes rarely)."""
        self.last_note: tuple[bytes, int] | None = None
        """The last notification on ``/log`` and its time: again to each new subscriber (the
        channel is advertised with its first message, which a client subscribing then misses)."""
        self.video_subscribers = 0
        self.video_task: asyncio.Task[None] | None = None

    def _channel(self, spec: ChannelSpec) -> foxglove.Channel:
        channel = self.channels.get(spec.topic)
        if channel is None:
            channel = self.channels[spec.topic] = foxglove.Channel(
                f"{self.prefix}{spec.topic}",
                message_encoding=schemas.MESSAGE_ENCODING,
                schema=foxglove.Schema(
                    name=spec.schema_name,
                    encoding=schemas.SCHEMA_ENCODING,
                    data=spec.schema_bytes(),
                ),
                context=self.context,
            )
        return channel

    def log(self, spec: ChannelSpec, data: bytes, time_ns: int) -> None:
        self._channel(spec).log(data, log_time=time_ns)

    def state(self, change: StateChange, now: int) -> None:
        """A ``/state`` change, as the recorder writes it; nothing when it did not change."""
        if self.states.get(change.what) == change:
            return
        self.states[change.what] = change
        self.log(schemas.STATE, change.encode(), now)

    def close(self) -> None:
        if self.video_task is not None:
            self.video_task.cancel("platform gone")
        for channel in self.channels.values():
            channel.close()


class FoxgloveLive(Actor):
    """The Foxglove WebSocket server and its channels, one set per connected platform."""

    name = "foxglove"

    def __init__(self, ctx: StationContext) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self.port = 0
        """The bound port (the kernel's choice for 0), once serving."""
        self.serving = asyncio.Event()
        self.platforms: dict[str, _PlatformChannels] = {}
        self.video_units = 0
        self._wake = asyncio.Event()
        """Set when a platform's telemetry has a snapshot not yet projected."""
        self._context: foxglove.Context | None = None
        self._server: Any = None
        self.guard: OriginGuard | None = None

    async def run(self) -> None:
        config = self.ctx.config.foxglove
        loop = asyncio.get_running_loop()
        self._context = foxglove.Context()
        port = config.port if PORT_OVERRIDE is None else PORT_OVERRIDE
        try:
            # The SDK's server behind the Origin/Host guard (stationd.foxglove_guard).
            self._server = await asyncio.to_thread(
                foxglove.start_server,
                name=f"brasidas-station {self.ctx.config.station.id}",
                host=UPSTREAM_HOST,
                port=0,
                capabilities=[],  # read-only: no client publishing, parameters or services
                server_listener=_Listener(loop, self),
                context=self._context,
            )
            self.guard = guard_for(self.ctx.config, UPSTREAM_HOST, int(self._server.port), port)
            await self.guard.start()
        except Exception as err:  # the port taken: the station runs on without it
            _LOGGER.error("foxglove: cannot serve on %s:%d: %s", config.host, port, err)
            if self._server is not None:
                await asyncio.to_thread(self._server.stop)
                self._server = None
            return
        self.port = self.guard.port
        self.serving.set()
        _LOGGER.info("foxglove: serving ws://%s:%d", config.host, self.port)
        self.subscribe(topics.PLATFORM_CONNECTED, self._on_connected)
        self.subscribe(topics.PLATFORM_DISCONNECTED, self._on_disconnected)
        self.subscribe(topics.STATION_NOTIFICATIONS, self._on_notification)
        self.subscribe(topics.COMMAND_SENT, self._on_command)
        for platform_id in list(self.ctx.connections):
            self._add(platform_id)
        self.subscribe(topics.TELEMETRY_SNAPSHOTS, self._on_snapshot)
        try:
            while True:
                await self._wake.wait()
                self._wake.clear()
                for platform in list(self.platforms.values()):
                    await self._project(platform)
        finally:
            for platform in self.platforms.values():
                platform.close()
            self.platforms.clear()
            self.serving.clear()
            server, self._server = self._server, None
            if server is not None:  # a crash (restarted): the next run binds again
                server.stop()
            if self.guard is not None:
                await self.guard.close()

    async def async_stop(self) -> None:
        if self.guard is not None:
            await self.guard.close()
        server, self._server = self._server, None
        if server is not None:
            await asyncio.to_thread(server.stop)

    # ------------------------------------------------------------------ platforms (loop)

    def _add(self, platform_id: str) -> None:
        if platform_id not in self.platforms and self._context is not None:
            # The recordings' names (``/navcam``) go to one platform; any other connected
            # meanwhile is told apart by its id (``/rover-2/navcam``), as all are with
            # ``foxglove.platform_prefix``.
            taken = any(not platform.prefix for platform in self.platforms.values())
            prefix = self.ctx.config.foxglove.platform_prefix or taken
            if taken:
                _LOGGER.info(
                    "foxglove: %s served as /%s/...: the recordings' names are another's",
                    platform_id,
                    platform_id,
                )
            self.platforms[platform_id] = _PlatformChannels(
                platform_id, self._context, prefix=prefix
            )

    def _on_connected(self, link: PlatformLink) -> None:
        self._add(link.platform_id)

    def _on_disconnected(self, link: PlatformLink) -> None:
        platform = self.platforms.pop(link.platform_id, None)
        if platform is not None:
            platform.close()

    def _on_notification(self, note: StationNotification) -> None:
        platform = self.platforms.get(note.platform_id)
        if platform is None:
            return
        time_ns = int(note.time * 1e9)
        level = schemas.LOG_WARNING if note.active else schemas.LOG_INFO
        text = f"{note.code} {note.name}: {note.message}{'' if note.active else ' (cleared)'}"
        data = schemas.encode_log(time_ns, level, note.name, text)
        platform.last_note = (data, time_ns)
        platform.log(schemas.LOG_CHANNEL, data, time_ns)

    def _on_command(self, sent: CommandSent) -> None:
        platform = self.platforms.get(sent.platform_id)
        if platform is not None:
            now = time.time_ns()
            platform.log(schemas.COMMANDS, schemas.encode_command(sent.command), now)

    def _on_snapshot(self, message: TelemetrySnapshot) -> None:
        platform = self.platforms.get(message.platform_id)
        if platform is not None:
            platform.pending = message.snapshot
            self._wake.set()

    async def _project(self, platform: _PlatformChannels) -> None:
        """The newest snapshot onto the channels (the shared projection): what changed, and
        every :data:`REPUBLISH_NS` what did not, so a client that subscribes later gets it."""
        snapshot, platform.pending = platform.pending, None
        if snapshot is None:
            return
        now = time.time_ns()
        again = frozenset(
            cls for cls in snapshot.sections if now - platform.logged_at.get(cls, 0) >= REPUBLISH_NS
        )
        messages, changes = projection.channel_messages(
            platform.previous, snapshot, now, again=again
        )
        for value, old in projection.changed_sections(platform.previous, snapshot):
            if value != old or type(value) in again:
                platform.logged_at[type(value)] = now
        platform.previous = snapshot
        for change in changes:
            platform.state(change, now)
        for message in messages:
            platform.log(message.spec, message.data, message.time_ns)
        # A revision counts as published only once fetched: a fetch that failed (a slow link, a
        # timeout) is tried again at the next snapshot, not left until the robot's next change.
        autonomy = snapshot.get(Autonomy)
        if autonomy is not None and autonomy.map_rev != platform.map_rev:
            if await self._map(platform):
                platform.map_rev = autonomy.map_rev
        view = snapshot.get(LidarView)
        if view is not None and view.grid_rev and view.grid_rev != platform.grid_rev:
            if await self._grid(platform):
                platform.grid_rev = view.grid_rev

    async def _map(self, platform: _PlatformChannels) -> bool:
        """The route and areas (``/map``), fetched when their revision moves; False: not fetched."""
        try:
            answer = await self.ctx.api.call_local("map_get", platform_id=platform.platform_id)
        except (RpcError, ConnectionError, TimeoutError):
            return False
        if isinstance(answer, dict) and answer.get("map") is not None:
            platform.map_data = schemas.encode_geojson(answer["map"])
            platform.log(schemas.MAP, platform.map_data, time.time_ns())
        return True

    async def _grid(self, platform: _PlatformChannels) -> bool:
        """The occupancy grid (``/grid``, foxglove.Grid), fetched when its revision moves;
        False: not fetched."""
        try:
            answer = await self.ctx.api.call_local(
                "perception_grid", platform_id=platform.platform_id
            )
            if not (isinstance(answer, dict) and answer.get("rev")):
                return False
            message = projection.grid_message(grid_from_json(answer), time.time_ns())
        except (RpcError, ConnectionError, TimeoutError):
            return False
        except GridRefused:
            return True  # a grid this station refuses (too big, malformed) is not asked again
        platform.grid_data = message.data
        platform.log(message.spec, message.data, message.time_ns)
        return True

    # ------------------------------------------------------------------ video (loop)

    def subscribed(self, topic: str, delta: int) -> None:
        """A client subscribed to (1) or left (-1) ``topic``; the NavCam is fetched while
        anyone watches it, and a new subscriber to the map, the grid (or the log) gets the
        current one (the last notification): each is advertised with its first message, which
        a client subscribing then misses."""
        for platform in self.platforms.values():
            if topic == f"{platform.prefix}{schemas.MAP.topic}" and delta > 0:
                if platform.map_data is not None:
                    platform.log(schemas.MAP, platform.map_data, time.time_ns())
            if topic == f"{platform.prefix}{schemas.OCCUPANCY_GRID.topic}" and delta > 0:
                if platform.grid_data is not None:
                    platform.log(schemas.OCCUPANCY_GRID, platform.grid_data, time.time_ns())
            if topic == f"{platform.prefix}{schemas.LOG_CHANNEL.topic}" and delta > 0:
                if platform.last_note is not None:
                    platform.log(schemas.LOG_CHANNEL, *platform.last_note)
            if topic == f"{platform.prefix}{schemas.NAVCAM.topic}":
                platform.video_subscribers = max(0, platform.video_subscribers + delta)
                if platform.video_subscribers and platform.video_task is None:
                    platform.video_task = asyncio.get_running_loop().create_task(
                        self._video(platform), name=f"foxglove:video:{platform.platform_id}"
                    )
                elif not platform.video_subscribers and platform.video_task is not None:
                    platform.video_task.cancel("no subscriber")
                    platform.video_task = None

    async def _video(self, platform: _PlatformChannels) -> None:
        feeds = self.ctx.video_feeds
        if feeds is None or not self.ctx.config.foxglove.video:
            return
        try:
            feed = await feeds.open_feed(platform.platform_id)
        except Exception as err:  # refused, lost, or the platform has no NavCam
            _LOGGER.warning("foxglove: no NavCam from %s: %s", platform.platform_id, err)
            platform.video_task = None  # the next subscription tries again
            return
        viewer = Viewer(feed.number)
        remove = feed.fanout.add(viewer)

        async def send(message: bytes) -> None:
            # The viewer starts each run at a keyframe (its GOP replay, or after a cutback).
            _kind, _flags, _feed, _seq, capture_ms, arrival_ms = HEADER.unpack_from(message)
            time_ns = int((capture_ms or arrival_ms) * 1e6)
            self.video_units += 1
            data = schemas.encode_video(time_ns, message[HEADER.size :])
            platform.log(schemas.NAVCAM, data, time_ns)

        try:
            await pump(viewer, send)
        finally:
            remove()
            feeds.release_feed(platform.platform_id)


async def async_setup(ctx: StationContext) -> None:
    if not ctx.config.foxglove.enabled:
        return
    live = FoxgloveLive(ctx)
    ctx.supervisor.start(live)
