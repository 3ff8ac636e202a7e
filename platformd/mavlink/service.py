"""The MAVLink endpoint's service: UDP transport, the bus, and the platform's decisions.

Datagrams go to :class:`~platformd.mavlink.vehicle.MavlinkVehicle` (sans-IO); what it asks
the platform is decided here with the same parts a station's request goes through:

- a ground station that commands anything is a *session* in ``ctx.sessions`` (station id
  ``gcs<SYSID>@HOST:PORT``), kept alive by its messages, so the command authority, the mode
  arbiter and the failsafe ladder treat it as they treat a station: it claims free control by
  commanding, an observer is refused with the holder's id, a station's ``--force`` takes
  control back, and a silent ground station's session times out (``signaling.session_timeout``);
- MANUAL is the manual override (system command 10.0 through the command router); MANUAL_CONTROL
  from its holder goes on ``TELEOP_VELOCITY``, so the motion arbiter's deadman, the speed cap
  and the failsafe ladder apply as to ``$PVEL``;
- a mission becomes the route through the patrol's ``set_waypoints``; a fence reshapes the map
  with ``update_map``'s checks (plus the route's).
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import time
from collections.abc import Mapping
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas import annunciator, topics
from brasidas.actor import Actor
from brasidas.annunciator import Annunciator
from brasidas.autonomy.route import RouteError
from brasidas.codecs.commands import MANUAL_OVERRIDE
from brasidas.codecs.telemetry_schema import Snapshot
from brasidas.config import PlatformConfig, TelemetryReceiverSection
from brasidas.messages import (
    Attitude,
    ControllerStatus,
    ControlState,
    FailsafeState,
    FailsafeStep,
    GpsFix,
    GpsFixLost,
    ImuStatus,
    MotionState,
    OverrideState,
    PatrolState,
    PatrolStatus,
    PoseEstimate,
    SessionClosed,
    Velocity,
)
from platformd.context import PlatformContext
from platformd.mavlink import arming, parameters
from platformd.mavlink.missions import (
    FENCE,
    MISSION,
    FencePlan,
    MissionItem,
    MissionRefused,
    fence_from_items,
    items_from_fence,
    items_from_route,
    route_from_items,
)
from platformd.mavlink.modes import FlightMode
from platformd.mavlink.parameters import SetParameter, WritableParameters, parameters_path
from platformd.mavlink.signing_state import SigningStateFile, gps_timestamp, signing_state_path
from platformd.mavlink.vehicle import (
    CameraInfo,
    GoTo,
    ManualInput,
    MavlinkVehicle,
    Peer,
    Request,
    SetCurrent,
    SetMode,
    Severity,
    StartVideo,
    UploadItems,
)
from platformd.session_table import Session

_LOGGER = logging.getLogger(__name__)

TICK = 0.05
VIDEO_CHARGE_INTERVAL = 1.0
"""Seconds between charges of a ground station's video to its address."""
"""Seconds between the vehicle's ticks: telemetry due times and mission item re-requests."""
FENCE_KEEPOUT_PREFIX = "fence-"
WARNINGS_INTERVAL = 1.0
"""Seconds between evaluations of the group 90 warnings."""
BATTERY_HYSTERESIS_V = 0.4
"""The low battery warning clears this far above ``telemetry.battery_low_v``."""
_SEVERITIES = {
    annunciator.LINK_LOST: Severity.CRITICAL,
    annunciator.LOW_BATTERY: Severity.CRITICAL,
    annunciator.CONTROLLER_OVER_TEMPERATURE: Severity.ERROR,
    annunciator.STREAM_FAILED: Severity.ERROR,
    annunciator.PATROL_HOLDING: Severity.NOTICE,
}
"""MAV_SEVERITY of each group 90 warning; the others are WARNING."""
FENCE_CHECK_INTERVAL = 1.0
"""Seconds between checks of the pose against the map (SYS_STATUS's geofence health)."""


class MavlinkService(Actor):
    """Owns the UDP endpoint and the vehicle; decides what ground stations ask."""

    name = "mavlink"

    def __init__(self, ctx: PlatformContext, key: bytes | None) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        config = ctx.config.mavlink
        self.config = config
        navcam = ctx.config.navcam
        camera = (
            CameraInfo(
                navcam.width,
                navcam.height,
                navcam.framerate,
                navcam.bitrate_kbps,
                navcam.port,
                framerate_now=self._navcam_framerate,
            )
            if config.camera and navcam.enabled
            else None
        )
        self.vehicle = MavlinkVehicle(
            config.system_id,
            targets=tuple(_peer(target) for target in config.targets),
            key=key,
            allow_unsigned_control=config.allow_unsigned_control,
            link_timeout=config.link_timeout,
            upload_window=config.upload_window,
            rates=(config.heartbeat_hz, config.position_hz, config.status_hz),
            camera=camera,
            wall_clock=time.time,
            mission_items=self.mission_items,
            ledger=ctx.egress,
        )
        self.vehicle.state.params = config_parameters(ctx.config)
        self.vehicle.safety_request = arming.safety_request
        self.vehicle.param_request = parameters.param_request
        self.parameters = WritableParameters(parameters_path(config.parameters_file))
        """FENCE_OPTIONS, as ground stations set it (restored in :meth:`open`)."""
        self.vehicle.state.gps_present = ctx.config.gps.enabled
        self.vehicle.state.motor_present = ctx.config.motor.enabled
        self.transport: asyncio.DatagramTransport | None = None
        self.port = 0
        """The bound UDP port (the kernel's choice for 0)."""
        self.sessions: dict[tuple[Peer, int], Session] = {}
        self.counters: dict[str, int] = dict.fromkeys(
            ("manual_control", "manual_control_ignored", "send_errors"), 0
        )
        self._requests: asyncio.Queue[Request] = asyncio.Queue(maxsize=64)
        self._uploaded: tuple[Any, list[MissionItem]] | None = None
        """The last accepted mission's route and items: downloads return them verbatim."""
        self._uploaded_seqs: tuple[int, ...] = ()
        """Its waypoints' item numbers (MISSION_CURRENT)."""
        self._video_sessions: dict[str, tuple[Peer, int]] = {}
        """Video a ground station's request started, by session: its requester and the bytes
        charged to the requester's address so far (brasidas.admission.SourceLedger)."""
        self._video_charged_at = 0.0
        self._override = OverrideState(False)
        self._patrol_state: PatrolState | None = None
        self._guided: FlightMode | None = None
        """GUIDED or RTL while going to a point (or stopped at it); None otherwise."""
        telemetry = ctx.config.telemetry
        # The station's group 90 warnings (brasidas.annunciator), from the platform's own
        # telemetry (the link's two, degraded and control taken, are a station's view:
        # CONTROL_STATE has its own text).
        self.annunciator = Annunciator(
            TelemetryReceiverSection(
                battery_low_v=telemetry.battery_low_v,
                battery_clear_v=telemetry.battery_low_v + BATTERY_HYSTERESIS_V,
            )
        )
        self._fence_checked = -FENCE_CHECK_INTERVAL
        self._uploaded_fence: tuple[int, list[MissionItem]] | None = None
        """The last accepted fence's items and the map revision it made."""
        self._signing_state = SigningStateFile(
            self.vehicle.signatures, signing_state_path(config.signing_state_file)
        )
        self.prearm_said: tuple[str, ...] = ()
        """The failing pre-arm checks last said in a STATUSTEXT (platformd.mavlink.arming)."""

    def _navcam_framerate(self) -> float:
        """The NavCam's framerate now (idle or engaged), the configured one without media."""
        media = self.ctx.media
        if media is not None and media.navcam is not None:
            return float(media.nav_camera().get("framerate", self.ctx.config.navcam.framerate))
        return float(self.ctx.config.navcam.framerate)

    # ------------------------------------------------------------------ lifecycle

    async def open(self) -> None:
        """Bind the UDP socket (before the daemon says it is up: tests read ``port``) after
        taking the saved signing state."""
        await self._signing_state.restore()
        await parameters.restore(self)
        loop = asyncio.get_running_loop()
        transport, _ = await loop.create_datagram_endpoint(
            lambda: _Protocol(self),
            local_addr=(self.config.host, self.config.port),
        )
        self.transport = transport
        self.port = transport.get_extra_info("sockname")[1]
        _LOGGER.info(
            "MAVLink endpoint on %s:%d (system %d), telemetry to %s",
            self.config.host,
            self.port,
            self.config.system_id,
            ", ".join(self.config.targets) or "whoever talks to it",
        )
        if self.vehicle.key is None and not self.config.allow_unsigned_control:
            _LOGGER.warning(
                "MAVLink: no mavlink.signing_key_file and unsigned control not allowed: "
                "ground stations may watch but not command"
            )
        elif self.config.allow_unsigned_control:
            _LOGGER.warning("MAVLink: unsigned control allowed: anyone reaching the port commands")

    async def run(self) -> None:
        if self.transport is None:
            await self.open()
        self.subscribe(topics.GPS_FIX, self._on_fix)
        self.subscribe(topics.GPS_FIX_LOST, self._on_fix_lost)
        self.subscribe(topics.POSE, self._on_pose)
        self.subscribe(topics.ATTITUDE, self._on_attitude)
        self.subscribe(topics.IMU_STATUS, self._on_imu)
        self.subscribe(topics.CONTROLLER_STATUS, self._on_controller)
        self.subscribe(topics.OVERRIDE_STATE, self._on_override)
        self.subscribe(topics.PATROL_STATUS, self._on_patrol)
        self.subscribe(topics.FAILSAFE_STATE, self._on_failsafe)
        self.subscribe(topics.CONTROL_STATE, self._on_control)
        self.subscribe(topics.MOTION_STATE, self._on_motion)
        self.subscribe(topics.SESSION_CLOSED, self._on_session_closed)
        self.on_remove(arming.follow(self))
        try:
            async with asyncio.TaskGroup() as group:
                group.create_task(self._tick_forever(), name="mavlink-tick")
                group.create_task(self._decide_forever(), name="mavlink-requests")
                group.create_task(self._annunciate_forever(), name="mavlink-warnings")
                group.create_task(self._signing_state.save_forever(), name="mavlink-signing")
        finally:
            self.close()
            await self._signing_state.save_at_stop()

    async def async_stop(self) -> None:
        self.close()

    def close(self) -> None:
        """Close the socket and end the ground stations' sessions. Idempotent."""
        if self.transport is not None:
            self.transport.close()
            self.transport = None
        for session in list(self.sessions.values()):
            self._end_session(session, "MAVLink endpoint stopped")

    async def _tick_forever(self) -> None:
        loop = asyncio.get_running_loop()
        proximity = None
        if self.ctx.config.lidar.enabled:  # OBSTACLE_DISTANCE for QGroundControl (issue 30)
            from platformd.lidar_models import MODELS
            from platformd.mavlink.proximity import ObstacleDistanceSender

            reach = MODELS[self.ctx.config.lidar.model].range_m
            proximity = ObstacleDistanceSender(self.ctx.bus, self.vehicle, reach)
        while True:
            self.vehicle.tick(loop.time())
            if proximity is not None:
                proximity.tick(loop.time())
            if loop.time() - self._video_charged_at >= VIDEO_CHARGE_INTERVAL:
                self.charge_video(loop.time())
            self.flush()
            await asyncio.sleep(TICK)

    async def _annunciate_forever(self) -> None:
        loop = asyncio.get_running_loop()
        while True:
            await asyncio.sleep(WARNINGS_INTERVAL)
            self.annunciate(loop.time())

    def annunciate(self, now: float) -> None:
        """STATUSTEXT for each group 90 warning raised or cleared since the last call."""
        snapshot = Snapshot(self.ctx.telemetry.build())
        arming.refresh(self, snapshot)
        for change in self.annunciator.evaluate(snapshot, 0.0, None, now):
            warning = change.warning
            if change.active:
                severity = _SEVERITIES.get(warning.code, Severity.WARNING)
                self.vehicle.statustext(severity, f"{warning.code} {warning.message}")
            else:
                self.vehicle.statustext(Severity.INFO, f"{warning.code} cleared: {warning.message}")
        self.flush()

    async def _decide_forever(self) -> None:
        while True:
            request = await self._requests.get()
            try:
                await self._decide(request)
            except Exception:
                _LOGGER.exception("MAVLink: %s failed", type(request).__name__)
            self.flush()

    # ------------------------------------------------------------------ datagrams

    def datagram_received(self, data: bytes, peer: Peer) -> None:
        """One datagram (on the event loop)."""
        now = asyncio.get_running_loop().time()
        peer = (str(peer[0]), int(peer[1]))
        requests = self.vehicle.feed(data, peer, now)
        link = self.vehicle.links.get(peer)
        if link is not None and link.last_trusted == now:
            self._refresh_sessions(peer)
        for request in requests:
            if isinstance(request, ManualInput):
                self._manual_control(request)
            elif self._requests.full():
                _LOGGER.warning("MAVLink: request dropped (%s): too many waiting", request)
            else:
                self._requests.put_nowait(request)
        self.flush()

    def flush(self) -> None:
        """Send what the vehicle has queued (answers, STATUSTEXT) now."""
        transport = self.transport
        datagrams = self.vehicle.take()
        if transport is None:
            return
        for data, peer in datagrams:
            try:
                transport.sendto(data, peer)
            except OSError:
                self.counters["send_errors"] += 1

    # ------------------------------------------------------------------ ground station sessions

    def session_for(self, request: Request) -> Session:
        """The ground station's session (opened on its first request)."""
        key = (request.peer, request.system)
        session = self.sessions.get(key)
        if session is not None and self.ctx.sessions.get(session.session_id) is not None:
            return session
        host, port = request.peer
        now = time.monotonic()
        session = Session(
            f"mavlink-{request.system}-{host}-{port}",
            f"gcs{request.system}@{host}:{port}",
            host,
            None,
            now,
            now,
        )
        self.sessions[key] = session
        self.ctx.sessions.open(session)  # announced: its close will be too
        _LOGGER.info("MAVLink: session of ground station %s opened", session.station_id)
        return session

    def _refresh_sessions(self, peer: Peer) -> None:
        """A trusted message from ``peer``: its sessions are alive (a spoofed unsigned one
        never holds off the session timeout or the failsafe ladder)."""
        now = time.monotonic()
        for (session_peer, _system), session in self.sessions.items():
            if session_peer == peer:
                session.last_seen = now

    def _end_session(self, session: Session, reason: str) -> None:
        self.ctx.sessions.close(session.session_id, reason)

    def _on_session_closed(self, event: SessionClosed) -> None:
        for key, session in list(self.sessions.items()):
            if session.session_id == event.session_id:
                del self.sessions[key]
        self._video_sessions.pop(event.session_id, None)

    def holder_system(self) -> int:
        """The controlling ground station's system id, 0 when a station (or nobody) holds it."""
        controller = self.ctx.authority.controller
        for (_peer, system), session in self.sessions.items():
            if controller is not None and controller.session_id == session.session_id:
                return system
        return 0

    # ------------------------------------------------------------------ decisions

    async def _decide(self, request: Request) -> None:
        if isinstance(request, SetMode):
            await self._set_mode(request)
        elif isinstance(request, UploadItems):
            await self._upload(request)
        elif isinstance(request, StartVideo):
            await self._start_video(request)
        elif isinstance(request, SetCurrent):
            self._set_current(request)
        elif isinstance(request, arming.SafetyCommand):
            await arming.decide(self, request)
        elif isinstance(request, GoTo):
            await self._go_to(request, FlightMode.GUIDED)
        elif isinstance(request, SetParameter):
            await parameters.decide(self, request)

    async def _go_to(self, request: GoTo | SetMode, mode: FlightMode) -> None:
        """GUIDED's point or RTL's home through the patrol's ``go_to_point`` (the planner,
        around keep-outs; stops there), for the control holder only."""
        vehicle = self.vehicle
        what = "go to" if mode is FlightMode.GUIDED else "RTL"
        refusal = self.refused(request, what)
        if refusal is not None:
            vehicle.answer_command(
                request, mavlink.MAV_RESULT_DENIED, refusal, holder_system=self.holder_system()
            )
            return
        patrol = self.ctx.patrol
        if patrol is None:
            vehicle.answer_command(request, mavlink.MAV_RESULT_UNSUPPORTED, "no patrol here")
            return
        if isinstance(request, GoTo):
            point, label = (request.latitude, request.longitude), "guided"
        elif vehicle.state.home is not None:
            point, label = vehicle.state.home[:2], "home"
        else:
            vehicle.answer_command(request, mavlink.MAV_RESULT_FAILED, "RTL: no home yet")
            return
        try:
            await patrol.go_to_point(point[0], point[1], label)
        except RouteError as exc:
            vehicle.answer_command(request, mavlink.MAV_RESULT_FAILED, f"{what} refused: {exc}")
            return
        session = self.session_for(request)
        if self._override.engaged and self._override.session_id == session.session_id:
            await self.ctx.commands.dispatch(MANUAL_OVERRIDE, "off", session)
        self._guided = mode
        self._update_mode()
        _LOGGER.info("MAVLink: %s %.7f, %.7f from %s", what, point[0], point[1], request.peer)
        if request.command is not None:
            vehicle.answer_command(request, mavlink.MAV_RESULT_ACCEPTED)

    def refused(self, request: Request, what: str) -> str | None:
        """Why the sender may not do ``what`` (the authority's refusal), or None."""
        return self.ctx.authority.refusal(self.session_for(request), what)

    async def _set_mode(self, request: SetMode) -> None:
        session = self.session_for(request)
        vehicle = self.vehicle
        if request.mode is FlightMode.MANUAL:
            result = await self.ctx.commands.dispatch(MANUAL_OVERRIDE, "on", session)
            if not result.accepted:
                vehicle.answer_command(
                    request,
                    mavlink.MAV_RESULT_DENIED,
                    result.reason,
                    holder_system=self.holder_system(),
                )
                return
            vehicle.answer_command(request, mavlink.MAV_RESULT_ACCEPTED)
            return
        if request.mode is FlightMode.HOLD and await arming.hold_for_anyone(self, request):
            return  # stopping never needs control
        if request.mode is FlightMode.RTL:
            await self._go_to(request, FlightMode.RTL)
            return
        refusal = self.refused(request, f"mode {request.mode.name}")
        if refusal is not None:
            vehicle.answer_command(
                request, mavlink.MAV_RESULT_DENIED, refusal, holder_system=self.holder_system()
            )
            return
        self._guided = FlightMode.GUIDED if request.mode is FlightMode.GUIDED else None
        patrol = self.ctx.patrol
        if request.mode is FlightMode.AUTO:
            if patrol is None:
                vehicle.answer_command(request, mavlink.MAV_RESULT_UNSUPPORTED, "no patrol here")
                return
            try:
                patrol.start_patrol()
            except RouteError as exc:
                vehicle.answer_command(request, mavlink.MAV_RESULT_FAILED, f"AUTO refused: {exc}")
                return
        elif patrol is not None:
            patrol.stop_patrol()
        if self._override.engaged and self._override.session_id == session.session_id:
            await self.ctx.commands.dispatch(MANUAL_OVERRIDE, "off", session)
        vehicle.answer_command(request, mavlink.MAV_RESULT_ACCEPTED)

    def _set_current(self, request: SetCurrent) -> None:
        """The patrol's next waypoint: mission item ``seq`` is route index ``seq - 1`` (item 0
        is home), through the patrol's own ``go_to_waypoint``, for the control holder only."""
        vehicle = self.vehicle
        refusal = self.refused(request, "set current waypoint")
        if refusal is not None:
            vehicle.answer_set_current(
                request, mavlink.MAV_RESULT_DENIED, refusal, holder_system=self.holder_system()
            )
            return
        patrol = self.ctx.patrol
        if patrol is None:
            vehicle.answer_set_current(request, mavlink.MAV_RESULT_UNSUPPORTED, "no patrol here")
            return
        try:
            if request.seq < 1:
                raise RouteError(f"item {request.seq} is home, not a waypoint")
            patrol.go_to_waypoint(request.seq - 1)
        except RouteError as exc:
            vehicle.answer_set_current(
                request, mavlink.MAV_RESULT_FAILED, f"set current refused: {exc}"
            )
            return
        _LOGGER.info("MAVLink: next waypoint %d, from %s", request.seq, request.peer)
        vehicle.answer_set_current(request, mavlink.MAV_RESULT_ACCEPTED)

    def _manual_control(self, request: ManualInput) -> None:
        """The joystick, from the override's holder only: the velocity path of ``$PVEL``."""
        session = self.sessions.get((request.peer, request.system))
        override = self._override
        if session is None or not override.engaged or override.session_id != session.session_id:
            self.counters["manual_control_ignored"] += 1
            return
        self.counters["manual_control"] += 1
        session.last_velocity = time.monotonic()
        self.bus.publish(topics.TELEOP_VELOCITY, Velocity(request.linear, request.angular))

    async def _upload(self, request: UploadItems) -> None:
        vehicle = self.vehicle
        what = "mission upload" if request.mission_type == MISSION else "fence upload"
        refusal = self.refused(request, what)
        if refusal is not None:
            vehicle.answer_upload(request, mavlink.MAV_MISSION_DENIED, refusal)
            return
        patrol = self.ctx.patrol
        if patrol is None:
            vehicle.answer_upload(request, mavlink.MAV_MISSION_UNSUPPORTED, "no patrol here")
            return
        items = list(request.items)
        try:
            if request.mission_type == MISSION:
                plan = route_from_items(items, skip_unsupported=self.config.skip_unsupported)
                route = await patrol.set_waypoints(plan.waypoint_items(), plan.laps, plan.home)
                self._uploaded = (route, items) if items else None
                self._uploaded_seqs = tuple(plan.seqs)
                self.vehicle.state.waypoint_seqs = self._uploaded_seqs
                text = mission_summary(route, plan.notes)
            else:
                fence = fence_from_items(items, union=self.parameters.fence_union)
                area = await patrol.reshape_map(self._fence_map(fence))
                self._uploaded_fence = (patrol.map_revision, items) if items else None
                text = f"fence: {len(area.keepouts)} keep-outs"
                if fence.inclusions > 1:
                    how = "union" if self.parameters.fence_union else "overlap"
                    text += f"; the boundary: the {how} of {fence.inclusions} inclusion polygons"
        except MissionRefused as exc:
            vehicle.answer_upload(request, exc.result, f"{what} refused: {exc}")
            return
        except ValueError as exc:  # RouteError, MapError: the patrol's own reasons
            vehicle.answer_upload(request, _position_result(), f"{what} refused: {exc}")
            return
        _LOGGER.info("MAVLink: %s accepted from %s", what, request.peer)
        vehicle.answer_upload(request, mavlink.MAV_MISSION_ACCEPTED, text)

    def _fence_map(self, fence: FencePlan) -> dict[str, Any]:
        """The map's GeoJSON with the fence's boundary (if any) and keep-outs."""
        patrol = self.ctx.patrol
        assert patrol is not None
        area = patrol.area
        if area is None:
            from brasidas.autonomy.areamap import MapError

            if fence.boundary is None:
                raise MapError("no map loaded: a fence needs an inclusion polygon")
            geojson: dict[str, Any] = {"type": "FeatureCollection", "features": []}
            features: list[dict[str, Any]] = [
                {"type": "Feature", "properties": {"role": "boundary"}, "geometry": {}}
            ]
        else:
            geojson = area.geojson()
            features = [
                feature for feature in geojson["features"] if _role(feature) not in ("keepout",)
            ]
        if fence.boundary is not None:
            for feature in features:
                if _role(feature) == "boundary":
                    feature["geometry"] = _polygon(fence.boundary)
        for index, ring in enumerate(fence.keepouts, start=1):
            features.append(
                {
                    "type": "Feature",
                    "id": f"{FENCE_KEEPOUT_PREFIX}{index}",
                    "properties": {"role": "keepout"},
                    "geometry": _polygon(ring),
                }
            )
        geojson["features"] = features
        return geojson

    async def _start_video(self, request: StartVideo) -> None:
        media = self.ctx.media
        if media is None or media.navcam is None:
            return
        session = self.session_for(request)
        if session.session_id in self._video_sessions:
            return
        self._video_sessions[session.session_id] = (request.peer, 0)
        # As a station's 10.1 with no host: the caller's own address, the NavCam's port.
        await media.start_stream(
            "navcam", request.peer[0], self.ctx.config.navcam.port, session_id=session.session_id
        )

    def charge_video(self, now: float) -> None:
        """The video each request started, charged to the requester's address (the one
        account of every byte sent on its behalf); a requester no longer trusted whose
        credit does not cover it loses its video (its session ends)."""
        self._video_charged_at = now
        media = self.ctx.media
        if media is None:
            return
        port = self.ctx.config.navcam.port
        for session_id, (peer, charged) in list(self._video_sessions.items()):
            sent = media.bytes_sent("navcam", peer[0], port)
            # A rebuilt pipeline or a re-added destination counts from 0 again.
            fresh = sent - charged if sent >= charged else sent
            self._video_sessions[session_id] = (peer, sent)
            link = self.vehicle.links.get(peer)
            trusted = link is not None and not link.stranger
            if fresh and not self.vehicle.ledger.stream_sent(peer[0], fresh, trusted, now):
                session = next(
                    (s for s in self.sessions.values() if s.session_id == session_id), None
                )
                if session is not None:
                    _LOGGER.warning("MAVLink: video to %s stopped: no longer trusted", peer[0])
                    self._end_session(session, "video: the ground station is no longer trusted")

    # ------------------------------------------------------------------ downloads

    def mission_items(self, mission_type: int) -> list[MissionItem]:
        """The stored route (MISSION) or the map's geometry (FENCE) as items."""
        patrol = self.ctx.patrol
        if patrol is None:
            return []
        if mission_type == MISSION:
            route = patrol.route
            if self._uploaded is not None and self._uploaded[0] == route:
                return self._uploaded[1]
            if not route.waypoints:
                return []
            home = route.home or self.vehicle.state.home
            return items_from_route(
                [(w.latitude, w.longitude) for w in route.waypoints],
                (home[0], home[1]) if home is not None else None,
                route.laps,
            )
        if mission_type == FENCE:
            uploaded = self._uploaded_fence
            if uploaded is not None and uploaded[0] == patrol.map_revision:
                return uploaded[1]
            area = patrol.area
            return items_from_fence(area.geojson()) if area is not None else []
        return []

    # ------------------------------------------------------------------ bus

    def _on_fix(self, fix: GpsFix) -> None:
        state = self.vehicle.state
        state.fix = fix
        if state.home is None:
            state.home = (fix.latitude, fix.longitude, fix.altitude_m or 0.0)
        self.vehicle.signing_clock.advance(gps_timestamp(fix.time))

    def _on_fix_lost(self, lost: GpsFixLost) -> None:
        self.vehicle.state.fix = None

    def _on_pose(self, pose: PoseEstimate) -> None:
        state = self.vehicle.state
        state.pose = pose
        if pose.time - self._fence_checked >= FENCE_CHECK_INTERVAL:
            self._fence_checked = pose.time
            state.inside_fence = self._inside_fence(pose)

    def _inside_fence(self, pose: PoseEstimate) -> bool | None:
        area = self.ctx.patrol.area if self.ctx.patrol is not None else None
        if area is None:
            return None
        from brasidas.autonomy.areamap import MapError  # loaded with the map already

        try:
            area.check_position(pose.latitude, pose.longitude)
        except MapError:
            return False
        return True

    def _on_attitude(self, attitude: Attitude) -> None:
        self.vehicle.state.attitude = attitude

    def _on_imu(self, status: ImuStatus) -> None:
        self.vehicle.state.imu_ok = status.ok

    def _on_controller(self, status: ControllerStatus) -> None:
        self.vehicle.state.controller = status

    def _on_motion(self, motion: MotionState) -> None:
        self.vehicle.state.throttle = motion.command.linear

    def _on_override(self, state: OverrideState) -> None:
        self._override = state
        self._update_mode()

    def _on_patrol(self, status: PatrolStatus) -> None:
        state = self.vehicle.state
        state.waypoint = status.waypoint
        state.waypoints = status.waypoints
        patrol = self.ctx.patrol
        uploaded = self._uploaded
        current = patrol is not None and uploaded is not None and uploaded[0] == patrol.route
        state.waypoint_seqs = self._uploaded_seqs if current else ()
        self._patrol_state = status.state
        self._update_mode()

    def _update_mode(self) -> None:
        patrol = self.ctx.patrol
        patrolling = self._patrol_state is PatrolState.PATROLLING
        detour = patrol is not None and patrol.detour is not None
        if self._override.engaged:
            mode = FlightMode.MANUAL
        elif self._guided is not None and (detour or not patrolling):
            mode = self._guided  # GUIDED or RTL: driving to the point, or stopped there
        elif patrolling:
            mode = FlightMode.AUTO
        else:
            mode = FlightMode.HOLD
        self.vehicle.state.mode = mode

    def _on_failsafe(self, failsafe: FailsafeState) -> None:
        # RELEASED is over: the override went, autonomy drives normally (not CRITICAL).
        self.vehicle.state.failsafe = failsafe.step is FailsafeStep.HOLD

    def _on_control(self, control: ControlState) -> None:
        if control.reason:
            holder = control.station_id or "nobody"
            self.vehicle.statustext(Severity.NOTICE, f"control: {holder} ({control.reason})")


class _Protocol(asyncio.DatagramProtocol):
    def __init__(self, service: MavlinkService) -> None:
        self.service = service

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        self.service.datagram_received(data, (str(addr[0]), int(addr[1])))

    def error_received(self, exc: Exception) -> None:
        # ICMP port unreachable from a target with no ground station running: expected.
        self.service.counters["send_errors"] += 1


# --------------------------------------------------------------------------- parameters


def config_parameters(config: PlatformConfig) -> list[tuple[str, float, int]]:
    """Every numeric and boolean config key as a read-only parameter: ``SECTION_KEY`` in
    capitals, shortened to MAVLink's 16 characters (section to 4 letters first, then the key)."""
    params: list[tuple[str, float, int]] = []
    seen: set[str] = set()
    for section_field in dataclasses.fields(config):
        section = getattr(config, section_field.name)
        for key_field in dataclasses.fields(section):
            value = getattr(section, key_field.name)
            if not isinstance(value, bool | int | float):
                continue
            name = f"{section_field.name}_{key_field.name}".upper()
            if len(name) > 16:
                name = f"{section_field.name[:4]}_{key_field.name}".upper()[:16]
            while name in seen:
                name = name[:15] + "~"
            seen.add(name)
            param_type = (
                mavlink.MAV_PARAM_TYPE_REAL32
                if isinstance(value, float)
                else mavlink.MAV_PARAM_TYPE_INT32
            )
            params.append((name, float(value), param_type))
    return params


# --------------------------------------------------------------------------- helpers


def _peer(target: str) -> Peer:
    host, _, port = target.rpartition(":")
    return (host, int(port))


def _role(feature: Mapping[str, Any]) -> str:
    properties = feature.get("properties") or {}
    return str(properties.get("role", ""))


def _polygon(ring: tuple[tuple[float, float], ...]) -> dict[str, Any]:
    coordinates = [[lon, lat] for lat, lon in ring]
    if coordinates[0] != coordinates[-1]:
        coordinates.append(coordinates[0])
    return {"type": "Polygon", "coordinates": [coordinates]}


def _position_result() -> int:
    """A waypoint or vertex the map refuses (outside the boundary, in a keep-out)."""
    return int(mavlink.MAV_MISSION_INVALID_PARAM5_X)


def mission_summary(route: Any, notes: list[str]) -> str:
    """An accepted mission's answer: waypoints, loop or laps, and each item skipped."""
    text = f"mission: {len(route.waypoints)} waypoints"
    if route.closed:
        text += ", closed" + (f", {route.laps} laps" if route.laps else "")
    elif route.laps:
        text += ", once"
    skipped = [note for note in notes if note.endswith(": skipped")]
    if skipped:
        text += "; " + "; ".join(skipped)
    return text
