"""The on-board recorder (issue 23): what the robot did, saw and was told, in MCAP files.

Subscribes to the bus (positions, velocities, motor commands, commands with their sender,
state changes), records every telemetry section at ``recorder.telemetry_hz``, and taps the
NavCam's encoded H.264 as it is sent (``media.tap_navcam``:
no second encoder, at the rate it streams; while no station watches, the NavCam runs for the
recorder alone at ``recorder.video_fps``, sent nowhere). Bus callbacks only
queue the message object; encoding and writing happen on the writer thread
(:class:`brasidas.recording.writer.Recorder`), so the event loop pays a queue put per message.

Stations list recordings with ``list_recordings`` (any session, observers too) and download
one over HTTP from the signaling port: ``GET /recordings/NAME`` with the session token in the
``X-Brasidas-Session`` header, ranges honoured (a download resumes).
"""

from __future__ import annotations

import asyncio
import logging
import secrets
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from aiohttp import web

from brasidas import topics
from brasidas.actor import Actor
from brasidas.codecs.jsonrpc import CallContext
from brasidas.codecs.telemetry_schema import SECTIONS, Autonomy, RecorderStatus, Section
from brasidas.messages import (
    CommandReceived,
    ControlState,
    FailsafeState,
    GpsFix,
    OverrideState,
    PatrolStatus,
    PoseEstimate,
    SessionClosed,
    SessionOpened,
    StreamStatus,
    Velocity,
)
from brasidas.perception.messages import FusedPosition, RobotScan
from brasidas.recording import SESSION_HEADER, projection, schemas
from brasidas.recording.projection import HDOP_TO_SIGMA_M, StateChange
from brasidas.recording.schemas import LOG_INFO, LOG_WARNING, ChannelSpec
from brasidas.recording.writer import (
    ACTIVE_SUFFIX,
    Quota,
    Recorder,
    list_recordings,
    recover_file,
    resolve_name,
)
from brasidas.rpc import peer_host
from brasidas.security import state_dir
from platformd.context import PlatformContext
from platformd.recording_download import send_file

if TYPE_CHECKING:
    from brasidas.perception.view import GridImage

_LOGGER = logging.getLogger(__name__)

REASON_MAX_CHARS = 60
LIDAR_HZ = 2.0
"""Lidar scans recorded a second (the sensor makes 10)."""
"""Telemetry carries this much of why recording stopped (an OSError may name a long path):
the section stays small (a stopped recorder on top of the fullest snapshot may take a datagram
of its own: the encoder splits by section)."""


def _index(channels: list[ChannelSpec]) -> dict[str, int]:
    return {spec.topic: i for i, spec in enumerate(channels)}


def _velocity(message: Velocity) -> bytes:
    return schemas.encode_velocity(message.linear, message.angular)


class PlatformRecorder(Actor):
    """Feeds the writer from the bus and the NavCam; serves the list and the downloads."""

    name = "recorder"
    stop_priority = -10
    """Stops last: it records the others' stopping."""

    def __init__(self, ctx: PlatformContext, directory: Path) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self.directory = directory
        config = ctx.config.recorder
        ctx.egress.download_rate = config.download_kib_s * 1024
        self.channels = schemas.all_channels()
        self.index = _index(self.channels)
        self.writer = Recorder(
            directory,
            self.channels,
            prefix=ctx.config.platform.id,
            quota=Quota(config.max_bytes, config.keep_days, config.min_free_bytes),
            rotate_seconds=config.rotate_minutes * 60,
            chunk_seconds=config.chunk_seconds,
            queue_messages=config.queue_messages,
            video_channel=self.index[schemas.NAVCAM.topic],
            on_event=self._on_writer_event,
        )
        self._loop: asyncio.AbstractEventLoop | None = None
        self._map_rev: int | None = None
        self._path: tuple[tuple[float, float], ...] | None = None
        self._patrol_state = ""
        self._scan_at = -1e9
        self._fused_at = -1e9
        self._map_task: asyncio.Task[None] | None = None

    # ------------------------------------------------------------------ lifecycle

    async def run(self) -> None:
        self._loop = asyncio.get_running_loop()
        self.writer.start()
        media = self.ctx.media
        untap = media.tap_navcam(self._on_access_unit) if media is not None else None
        if media is not None and untap is not None:
            self.on_remove(untap)
            # Recorded when nobody watches too (an unattended patrol), at its own rate.
            await media.record_navcam(self.ctx.config.recorder.video_fps)
        self._subscribe_all()
        self._log(LOG_INFO, "recorder", "recording started")
        period = 1.0 / self.ctx.config.recorder.telemetry_hz
        try:
            while True:
                await asyncio.sleep(period)
                self._record_telemetry()
        finally:
            if self._map_task is not None:
                self._map_task.cancel("recorder stopping")

    async def async_stop(self) -> None:
        """Finish the current file (in a thread: it compresses and syncs the last chunk)."""
        self._log(LOG_INFO, "recorder", "platform stopping")
        await asyncio.to_thread(self.writer.stop, 0.4)

    def counters(self) -> dict[str, int]:
        return {**self.writer.stats.counters(), "queued": self.writer.queued}

    def status_section(self) -> RecorderStatus:
        """The telemetry section: the station warns (90.23) when recording stopped."""
        stats = self.writer.stats
        reason = stats.reason
        return RecorderStatus(
            recording=stats.recording and not reason,
            reason=reason
            if len(reason) <= REASON_MAX_CHARS
            else reason[: REASON_MAX_CHARS - 1] + "…",
            dropped=stats.dropped,
            not_recorded=stats.not_recording,
        )

    def describe(self) -> dict[str, Any]:
        stats = self.writer.stats
        return {
            "recording": stats.recording,
            "reason": stats.reason,
            "current": stats.current,
            "directory": str(self.directory),
            "counters": self.counters(),
        }

    # ------------------------------------------------------------------ sources (event loop)

    def _submit(self, spec: ChannelSpec, payload: Any, encode: Any = None) -> None:
        self.writer.submit(self.index[spec.topic], time.time_ns(), payload, encode)

    def _subscribe_all(self) -> None:
        self.subscribe(topics.GPS_FIX, self._on_fix)
        self.subscribe(topics.POSE, self._on_pose)
        self.subscribe(topics.TELEOP_VELOCITY, self._velocity(schemas.TELEOP_VELOCITY))
        self.subscribe(topics.CMD_VEL, self._velocity(schemas.AUTONOMY_VELOCITY))
        self.subscribe(topics.MOTOR_COMMAND, self._velocity(schemas.MOTOR_COMMAND))
        self.subscribe(topics.COMMAND_RECEIVED, self._on_command)
        self.subscribe(topics.FAILSAFE_STATE, self._on_failsafe)
        self.subscribe(topics.CONTROL_STATE, self._on_control)
        self.subscribe(topics.OVERRIDE_STATE, self._on_override)
        self.subscribe(topics.STREAM_STATES, self._on_stream)
        self.subscribe(topics.SESSION_OPENED, self._on_session_opened)
        self.subscribe(topics.SESSION_CLOSED, self._on_session_closed)
        self.subscribe(topics.PATROL_STATUS, self._on_patrol)
        self.subscribe(topics.LIDAR_SCAN, self._on_scan)
        self.subscribe(topics.FUSED_POSE, self._on_fused_pose)
        self.subscribe(topics.OCCUPANCY_GRID, self._on_grid)

    def _velocity(self, spec: ChannelSpec) -> Any:
        def record(message: Velocity) -> None:
            self._submit(spec, message, _velocity)

        return record

    def _on_access_unit(self, data: bytes, keyframe: bool, captured_ns: int) -> None:
        """Streaming thread: queue the access unit (the writer encodes it)."""
        self.writer.submit(
            self.index[schemas.NAVCAM.topic],
            captured_ns,
            data,
            lambda unit: schemas.encode_video(captured_ns, unit),
            keyframe=keyframe,
        )

    def _on_fix(self, fix: GpsFix) -> None:
        now = time.time_ns()
        sigma = fix.hdop * HDOP_TO_SIGMA_M if fix.hdop is not None else None
        self.writer.submit(
            self.index[schemas.GPS.topic],
            now,
            fix,
            lambda f: schemas.encode_location(now, f.latitude, f.longitude, f.altitude_m, sigma),
        )

    def _on_pose(self, pose: PoseEstimate) -> None:
        now = time.time_ns()
        self.writer.submit(
            self.index[schemas.POSE.topic],
            now,
            pose,
            lambda p: schemas.encode_location(now, p.latitude, p.longitude, None, p.sigma_xy_m),
        )
        self.writer.submit(
            self.index[schemas.POSE_LOCAL.topic],
            now,
            pose,
            lambda p: schemas.encode_pose(now, p.x_m, p.y_m, p.yaw_rad),
        )

    def _on_scan(self, scan: RobotScan) -> None:
        """At most ``LIDAR_HZ`` scans a second (a revolution is a few kB of JSON)."""
        if scan.time - self._scan_at < 1.0 / LIDAR_HZ:
            return
        self._scan_at = scan.time
        now = time.time_ns()
        self._submit(
            schemas.LIDAR_SCAN,
            scan,
            lambda s: schemas.encode_laser_scan(now, s.bearings_deg, s.ranges_m),
        )

    def _on_fused_pose(self, pose: FusedPosition) -> None:
        """The lidar localization's pose, at most ``LIDAR_HZ`` a second: on the globe, and in
        the grid's frame (where ``/grid`` is drawn)."""
        if pose.time - self._fused_at < 1.0 / LIDAR_HZ:
            return
        self._fused_at = pose.time
        now = time.time_ns()
        self._submit(
            schemas.FUSED_POSE,
            pose,
            lambda p: schemas.encode_location(now, p.latitude, p.longitude, None, p.sigma_m),
        )
        self._submit(
            schemas.FUSED_POSE_LOCAL,
            pose,
            lambda p: schemas.encode_pose(now, p.x_m, p.y_m, p.yaw_rad, schemas.GRID_FRAME),
        )

    def _on_grid(self, image: GridImage) -> None:
        """The occupancy grid as ``foxglove.Grid``, as often as the platform remakes it."""
        now = time.time_ns()
        self._submit(schemas.OCCUPANCY_GRID, image, lambda i: projection.grid_message(i, now).data)

    def _on_command(self, message: CommandReceived) -> None:
        self._submit(schemas.COMMANDS, message, schemas.encode_command)
        verdict = "accepted" if message.accepted else f"refused: {message.reason}"
        self._log(
            LOG_INFO if message.accepted else LOG_WARNING,
            "commands",
            f"{message.name} {message.payload!r} from {message.station_id or 'the platform'}"
            f" ({verdict})",
        )

    def _state(self, what: str, state: str, station: str | None, reason: str, level: int) -> None:
        change = StateChange(what, state, station, reason)
        self._submit(schemas.STATE, change, StateChange.encode)
        by = f" ({station})" if station else ""
        self._log(level, what, f"{what} {state}{by}{': ' + reason if reason else ''}")

    def _on_failsafe(self, state: FailsafeState) -> None:
        level = LOG_INFO if state.step.value == "normal" else LOG_WARNING
        self._state("failsafe", state.step.value, state.station_id, state.reason, level)

    def _on_control(self, state: ControlState) -> None:
        self._state("control", "held" if state.station_id else "free", state.station_id,
                    state.reason, LOG_INFO)  # fmt: skip

    def _on_override(self, state: OverrideState) -> None:
        self._state(
            "override", "engaged" if state.engaged else "disengaged", state.station_id, "", LOG_INFO
        )

    def _on_stream(self, status: StreamStatus) -> None:
        level = LOG_WARNING if status.state == "failed" else LOG_INFO
        self._state(f"stream:{status.name}", status.state, None, status.reason, level)

    def _on_session_opened(self, event: SessionOpened) -> None:
        self._state("session", "opened", event.station_id, event.peer_host, LOG_INFO)

    def _on_session_closed(self, event: SessionClosed) -> None:
        self._state("session", "closed", event.station_id, event.reason, LOG_INFO)

    def _on_patrol(self, status: PatrolStatus) -> None:
        if status.path != self._path:
            self._path = status.path
            self._submit(schemas.ROUTE, status.path, schemas.encode_path)
        if status.state.value != self._patrol_state:
            self._patrol_state = status.state.value
            level = LOG_WARNING if status.state.value == "holding" else LOG_INFO
            self._state("patrol", status.state.value, None, status.reason, level)

    def _log(self, level: int, name: str, text: str) -> None:
        now = time.time_ns()
        self.writer.submit(
            self.index[schemas.LOG_CHANNEL.topic],
            now,
            text,
            lambda message: schemas.encode_log(now, level, name, message),
        )

    def _on_writer_event(self, level: int, text: str) -> None:
        """Writer thread: a warning (recording stopped, resumed) goes into the log channel
        too, once the loop has it."""
        loop = self._loop
        if loop is not None and not loop.is_closed():
            loop.call_soon_threadsafe(self._log, level, "recorder", text)

    def _record_telemetry(self) -> None:
        snapshot = self.ctx.telemetry.build()
        now = time.time_ns()
        for cls in SECTIONS:
            value = snapshot.get(cls)
            if isinstance(value, Section):
                # Encoded on the writer thread, as Foxglove live's (the shared projection).
                spec = projection.section_channel(cls)
                self.writer.submit(self.index[spec.topic], now, value, projection.encode_section)
        autonomy = snapshot.get(Autonomy)
        if isinstance(autonomy, Autonomy) and autonomy.map_rev != self._map_rev:
            self._map_rev = autonomy.map_rev
            self._record_map()

    def _record_map(self) -> None:
        if not self.ctx.rpc.has("get_map"):
            return
        if self._map_task is not None and not self._map_task.done():
            return
        self._map_task = asyncio.get_running_loop().create_task(
            self._fetch_map(), name="recorder:map"
        )

    async def _fetch_map(self) -> None:
        try:
            answer = await self.ctx.rpc.call_local("get_map")
        except Exception:
            _LOGGER.exception("recorder: get_map failed")
            return
        if isinstance(answer, dict) and answer.get("map") is not None:
            self._submit(schemas.MAP, answer["map"], schemas.encode_geojson)

    # ------------------------------------------------------------------ station side

    async def rpc_list_recordings(self, call: CallContext) -> dict[str, Any]:
        """Every recording (name, start, duration, size, channels) and the recorder's state."""
        items = await asyncio.to_thread(list_recordings, self.directory)
        return {**self.describe(), "recordings": items}

    async def http_download(self, request: web.Request) -> web.StreamResponse:
        """``GET /recordings/NAME``: one file, to an open session from the session's own host
        (as every RPC), ranges honoured; a symbolic link is no recording."""
        session = self.ctx.session(request.headers.get(SESSION_HEADER))
        if session is None:
            raise web.HTTPUnauthorized(text=f"a session token is needed ({SESSION_HEADER})")
        if peer_host(request) != session.peer_host:
            raise web.HTTPUnauthorized(text="the session was opened from another host")
        path = resolve_name(self.directory, request.match_info["name"])
        if path is None:
            raise web.HTTPNotFound(text="no such recording")
        if path.name.endswith(ACTIVE_SUFFIX):
            return await self._snapshot_download(request, path, session.peer_host)
        # Every download together at recorder.download_kib_s, charged to the caller's address.
        return await send_file(
            request,
            path,
            self.ctx.egress,
            session.peer_host,
            {"Content-Type": "application/octet-stream"},
        )

    async def _snapshot_download(
        self, request: web.Request, path: Path, host: str
    ) -> web.StreamResponse:
        """The file being written, as a complete MCAP up to its last closed chunk (summary
        and footer written): what readers open. A new copy each time: a range is of the copy it
        gets, so the station never resumes one (stationd.recordings); at the downloads' share."""
        copy = path.with_name(f".{path.name}.{secrets.token_hex(4)}.download")
        try:
            await asyncio.to_thread(recover_file, path, copy)
            return await send_file(
                request,
                copy,
                self.ctx.egress,
                host,
                {"Content-Type": "application/octet-stream"},
            )
        finally:
            copy.unlink(missing_ok=True)


def recordings_dir(ctx: PlatformContext) -> Path:
    configured = ctx.config.recorder.dir
    return Path(configured) if configured else state_dir() / "recordings"


async def async_setup(ctx: PlatformContext) -> None:
    if not ctx.config.recorder.enabled:
        return
    recorder = PlatformRecorder(ctx, recordings_dir(ctx))
    ctx.telemetry.add_counters("recorder", recorder.counters)
    ctx.telemetry.register(RecorderStatus, recorder.status_section)
    ctx.rpc.add("list_recordings", recorder.rpc_list_recordings)
    ctx.http_routes.append(web.get("/recordings/{name}", recorder.http_download))
    ctx.supervisor.start(recorder)
