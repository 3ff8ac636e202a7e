"""Media streams of the platform (R-11), each managed on its own (R-11.4).

``navcam`` (H.264 video out), ``audio_out`` (microphone, Opus), ``audio_in`` (the station's
voice to the speaker; the platform listens on ``audio.in_host:in_port``) and
``payload_camera`` (an RTSP camera forwarded without re-encoding), as configured.

A stream sends only after a station asked for it: system command 10.1 (payload: the station's
host, ``host=10.0.0.2``; empty means the caller's own address) starts every stream, 10.2 stops
and 10.3 pauses them all, and the signaling methods ``start_stream(name, host, port)``,
``pause_stream``, ``stop_stream`` and ``list_streams`` act on one (R-11.4). 10.5
``navcam=15`` sets a video stream's framerate for the current mode: the NavCam runs at
``navcam.idle_framerate`` (5 fps) while the manual override is disengaged and at
``navcam.framerate`` (30 fps) while it is engaged (seed ch. 10 §3.2).

Every state change is published on ``STREAM_STATES`` (telemetry marks a failed stream as a
fault); a failed stream is rebuilt with backoff by its supervisor task, the others go on.

Each session that starts a stream gets its own copy: the NavCam, the microphone and the payload
camera are sent to every destination asked for (``multiudpsink``), and the platform listens
for the station's voice while any session wants it. A session's stop (or its end) ends its
copy only; a stream stops when nobody wants it any more. Pausing and the framerate act on
every copy: control methods, for the station holding control (platformd.authority). A stream
paused stays paused until the station holding control resumes it: another's start adds its
copy, paused with the rest.

A station has a stream sent to its own address or to the platform's loopback, or to one of
``security.stream_destinations``: never to a third host (an amplifier) nor to another station
(doubling its traffic). A destination without a route is refused at the request, before it can
fail the sink that every station's copy shares.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import re
import socket
import time
from collections.abc import Awaitable, Callable, Coroutine
from typing import Any

from brasidas import topics
from brasidas.actor import Actor, wait_forever
from brasidas.codecs.commands import (
    AUTO_FRAMERATE,
    PAUSE_STREAMS,
    SET_FRAMERATE,
    START_STREAMS,
    STOP_STREAMS,
    STREAM_RETRIES,
    PayloadError,
    parse_payload,
    parse_switch,
)
from brasidas.codecs.jsonrpc import INVALID_PARAMS, CallContext, RpcError
from brasidas.config import PlatformConfig
from brasidas.media.audio import AudioIn, AudioOut, AudioSettings
from brasidas.media.bitrate import TRANSPORT_POLL_S
from brasidas.media.fanout import FanOutStream
from brasidas.media.gst import MediaUnavailable, gst
from brasidas.media.navcam import FrameratePolicy, navcam_settings, parse_framerate
from brasidas.media.pipeline import PipelineStream, StreamState
from brasidas.media.relay import ForwardSettings, RtspForward
from brasidas.media.video import AccessUnitSink, VideoOut
from brasidas.messages import CommandResult, OverrideState, SessionClosed, StreamStatus
from platformd.automation import report_switch
from platformd.commands import SystemCommand
from platformd.context import PlatformContext
from platformd.session_table import Session
from platformd.telemetry.methods import allowed_host

_LOGGER = logging.getLogger(__name__)

_HOSTNAME = re.compile(
    r"^(?=.{1,253}$)[A-Za-z0-9]([A-Za-z0-9-]{0,61}[A-Za-z0-9])?(\.[A-Za-z0-9-]{1,63})*$"
)


def preload(config: PlatformConfig) -> None:
    """When the NavCam starts with the daemon (the recorder's copy: :meth:`MediaService.
    record_navcam`), GStreamer imported and initialised (its registry read) and Gio for the
    repair sockets. Otherwise that waits for a station's first stream, as it did (~10 MB of
    resident memory a platform nobody watches does not spend). Without GStreamer, the stream
    reports it when built."""
    recorder = config.recorder
    if not (config.navcam.enabled and recorder.enabled and recorder.video_fps > 0):
        return
    try:
        gst()
    except MediaUnavailable:
        return
    from gi.repository import Gio  # noqa: F401  (brasidas.media.repair's GSocket)


class MediaService(Actor):
    """Owns the platform's streams and runs their supervisors."""

    name = "media"

    def __init__(self, ctx: PlatformContext) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self.streams: dict[str, PipelineStream] = {}
        self.viewers: dict[str, dict[str | None, tuple[str, int]]] = {}
        """Each stream's destinations, by the session that asked (None: the platform itself);
        for ``audio_in``, the platform's own listening address."""
        self.navcam: VideoOut | None = None
        navcam = ctx.config.navcam
        self.framerate = FrameratePolicy(
            engaged_fps=navcam.framerate, idle_fps=navcam.idle_framerate, limit=navcam.framerate
        )
        self._group: asyncio.TaskGroup | None = None
        self.paused: set[str] = set()
        """Streams paused by control: only the station holding control resumes them."""
        self.retry = True
        """Failed streams are rebuilt with backoff (10.10)."""
        self.record_fps = 0
        """The recorder's own NavCam copy while nobody watches (0: none): :meth:`record_navcam`."""
        if navcam.enabled:
            self.navcam = VideoOut(
                "navcam",
                navcam_settings(navcam, sim=ctx.config.sim.enabled),
                on_change=self._publish,
            )
            self.streams["navcam"] = self.navcam
        sim = ctx.config.sim.enabled
        audio = ctx.config.audio
        if audio.enabled:
            self.streams["audio_out"] = AudioOut(
                "audio_out",
                AudioSettings(
                    device=audio.source_device,
                    test_source=sim,
                    bitrate=audio.bitrate,
                    port=audio.out_port,
                ),
                on_change=self._publish,
            )
            self.streams["audio_in"] = AudioIn(
                "audio_in",
                host=audio.in_host,
                port=audio.in_port,
                device=audio.sink_device,
                sink="fakesink" if sim else "",
                on_change=self._publish,
            )
        camera = ctx.config.payload_camera
        if camera.enabled and camera.url:
            self.streams["payload_camera"] = RtspForward(
                "payload_camera",
                ForwardSettings(url=camera.url, latency_ms=camera.latency_ms, port=camera.port),
                on_change=self._publish,
            )

    # ------------------------------------------------------------------ lifecycle

    async def run(self) -> None:
        self.on_remove(
            self.ctx.commands.register(
                self.name,
                {
                    START_STREAMS: self._command_start,
                    STOP_STREAMS: self._command_stop,
                    PAUSE_STREAMS: self._command_pause,
                    SET_FRAMERATE: self._command_framerate,
                    AUTO_FRAMERATE: self._command_auto_framerate,
                    STREAM_RETRIES: self._command_retries,
                },
            )
        )
        self.subscribe(topics.OVERRIDE_STATE, self._on_override)
        self.subscribe(topics.SESSION_CLOSED, self._on_session_closed)
        report_switch(self.bus, "auto_framerate", self.framerate.auto)
        report_switch(self.bus, "stream_retries", self.retry)
        async with asyncio.TaskGroup() as group:
            self._group = group
            for stream in self.streams.values():
                group.create_task(stream.supervise(), name=f"media:{stream.name}")
            if self.navcam is not None:
                group.create_task(self._adapt_bitrate(self.navcam), name="media:bitrate")
            try:
                await wait_forever()
            finally:
                self._group = None

    async def _adapt_bitrate(self, navcam: VideoOut) -> None:
        """The NavCam's bitrate follows the receivers' reports (brasidas.media.bitrate)."""
        while True:
            await asyncio.sleep(TRANSPORT_POLL_S)
            kbps = navcam.adapt_bitrate(time.monotonic())
            if kbps is not None:
                _LOGGER.debug(
                    "navcam bitrate %d kbit/s (reported loss %.2f)", kbps, navcam.bitrate.loss
                )

    async def async_stop(self) -> None:
        """Stop every pipeline (their NULL state changes run in threads, in parallel)."""
        self.record_fps = 0  # a copy stopping meanwhile must not restart the recorder's
        await asyncio.gather(
            *(stream.stop() for stream in self.streams.values()), return_exceptions=True
        )

    # ------------------------------------------------------------------ bus

    def _publish(self, stream: PipelineStream) -> None:
        self.bus.publish(
            topics.STREAM_STATES,
            StreamStatus(
                name=stream.name,
                kind=stream.kind,
                state=stream.state.value,
                reason=stream.reason,
                destination=stream.destination() if stream.state is not StreamState.IDLE else "",
            ),
        )

    def _on_override(self, state: OverrideState) -> None:
        fps = self.framerate.set_override(state.engaged)
        if self.navcam is not None and self.navcam.nowhere:
            return  # the recorder's own copy keeps its rate until a station watches
        if self.navcam is not None and fps != self.navcam.settings.framerate:
            _LOGGER.info("navcam framerate %d fps", fps)
            self.navcam.set_framerate(fps)

    def _on_session_closed(self, event: SessionClosed) -> None:
        wanted = [
            name
            for name, viewers in self.viewers.items()
            if any(_owner(key) == event.session_id for key in viewers)
        ]
        for name in wanted:
            self._spawn(self.stop_stream(name, session_id=event.session_id), f"media:stop:{name}")

    def _spawn(self, work: Awaitable[Any], name: str) -> None:
        if self._group is None:
            # Not running (shutting down): the stop hook stops every stream anyway.
            if asyncio.iscoroutine(work):
                work.close()
            return
        self._group.create_task(_awaited(work), name=name)

    # ------------------------------------------------------------------ system commands

    async def _command_start(self, command: SystemCommand) -> CommandResult:
        try:
            host = host_from_payload(command.payload, _peer_host(command.session))
        except PayloadError as err:
            return CommandResult(False, str(err))
        refusal = self.destination_refusal(host, command.session)
        if refusal is not None:
            return CommandResult(False, refusal)

        async def start_all() -> CommandResult:
            states = {}
            for name in self.streams:
                states[name] = await self.start_stream(name, host, session_id=command.session_id)
            return _summary(states)

        return await self._in_group(start_all(), command)

    async def _command_stop(self, command: SystemCommand) -> CommandResult:
        async def stop_all() -> CommandResult:
            states = {}
            for name in self.streams:
                states[name] = await self.stop_stream(name, session_id=command.session_id)
            return _summary(states)

        return await self._in_group(stop_all(), command)

    async def _command_pause(self, command: SystemCommand) -> CommandResult:
        async def pause_all() -> CommandResult:
            return _summary({name: await self.pause_stream(name) for name in self.streams})

        return await self._in_group(pause_all(), command)

    async def _in_group(
        self, work: Coroutine[Any, Any, CommandResult], command: SystemCommand
    ) -> CommandResult:
        """Run a command's pipeline changes in this actor's task group: a caller that stops
        waiting (the router's timeout) leaves them to finish instead of cutting them short."""
        if not self.streams or self._group is None:
            work.close()
            return CommandResult(False, "this platform has no media streams running")
        task = self._group.create_task(_answer(work), name=f"media:{command.code}")
        return await asyncio.shield(task)

    async def _command_framerate(self, command: SystemCommand) -> CommandResult:
        try:
            values = parse_payload(command.payload)
        except PayloadError as err:
            return CommandResult(False, str(err))
        if not values:
            return CommandResult(False, "expected <stream>=<fps>, e.g. navcam=15")
        result = {}
        for name, raw in values.items():
            try:
                result[name] = self.set_framerate(name, raw)
            except ValueError as err:
                return CommandResult(False, str(err))
        return CommandResult(True, result=result)

    async def _command_auto_framerate(self, command: SystemCommand) -> CommandResult:
        """10.9: the NavCam's automatic 5/30 fps switch on or off (off keeps the current rate)."""
        try:
            on = parse_switch(command.payload)
        except PayloadError as err:
            return CommandResult(False, str(err))
        fps = self.framerate.set_auto(on)
        if self.navcam is not None and fps != self.navcam.settings.framerate:
            self.navcam.set_framerate(fps)
        report_switch(self.bus, "auto_framerate", on)
        return CommandResult(True, result={"auto_framerate": on, "navcam_fps": fps})

    async def _command_retries(self, command: SystemCommand) -> CommandResult:
        """10.10: rebuilding failed streams on or off."""
        try:
            on = parse_switch(command.payload)
        except PayloadError as err:
            return CommandResult(False, str(err))
        self.retry = on
        for stream in self.streams.values():
            stream.set_retry(on)
        report_switch(self.bus, "stream_retries", on)
        return CommandResult(True, result={"stream_retries": on})

    # ------------------------------------------------------------------ per-stream control

    def get(self, name: str) -> PipelineStream:
        stream = self.streams.get(name)
        if stream is None:
            known = ", ".join(self.streams) or "none"
            raise KeyError(f"no stream named '{name}' (streams: {known})")
        return stream

    async def start_stream(
        self,
        name: str,
        host: str = "",
        port: int = 0,
        *,
        session_id: str | None = None,
        copy: bool = False,
    ) -> StreamState:
        """Start (or resume) ``session_id``'s copy of a stream, sent to ``host:port`` (the
        stream's configured address for what is not given). A stream sent out goes to every
        session that started it, each at its own destination; ``audio_in`` listens while any
        session wants it. One session's start never moves another's copy. ``copy``: one more
        destination for the session (a second consumer at its station, ``view`` beside the
        console), its own until stopped by its port.
        """
        stream = self.get(name)
        viewers = self.viewers.setdefault(name, {})
        if isinstance(stream, FanOutStream):
            settings = stream.settings
            key = f"{session_id}{COPY_MARK}{port}" if copy and port else session_id
            copies = [k for k in viewers if k != session_id and _owner(k) == session_id]
            if key not in viewers and key != session_id and len(copies) >= COPIES_MAX:
                raise ValueError(f"stream '{name}': at most {COPIES_MAX} copies per station")
            viewers[key] = (host or settings.host, port or settings.port)
            recorded_only = stream.nowhere
            stream.set_destinations(list(viewers.values()))
            if recorded_only and stream is self.navcam:
                self._follow_policy()  # the first viewer after the recorder's own copy
        else:
            viewers[session_id] = ("", 0)  # the platform's own address: nothing to choose
        if name in self.paused and not self._controls(session_id):
            return stream.state  # its copy joins the paused stream: resuming is control
        self.paused.discard(name)
        return await stream.start()

    async def pause_stream(self, name: str) -> StreamState:
        """Pause every copy (control: the caller holds it); resumed by control only."""
        stream = self.get(name)
        state = await stream.pause()
        if state is StreamState.PAUSED:
            self.paused.add(name)
        return state

    def _controls(self, session_id: str | None) -> bool:
        """``session_id`` may resume a paused stream: the platform itself, the session holding
        control, or anyone while nobody does."""
        controller = self.ctx.authority.controller
        return session_id is None or controller is None or controller.session_id == session_id

    def destination_refusal(self, host: str, session: Session | None) -> str | None:
        """Why ``session`` may not have streams sent to ``host`` (a literal address or a host
        name), or None. The platform itself (``session`` None) sends anywhere."""
        if session is None:
            return None
        peer = _peer_host(session)
        allowed = self.ctx.config.security.stream_destinations
        if not (allowed_host(host, peer) or in_destinations(host, allowed)):
            return (
                f"streams go to the caller's own address ({peer}) or loopback, not {host} "
                "(security.stream_destinations names others)"
            )
        return unroutable(host)

    async def stop_stream(
        self, name: str, *, session_id: str | None = None, port: int = 0
    ) -> StreamState:
        """Stop ``session_id``'s copies of a stream (only the one sent to ``port`` when given);
        the stream stops when nobody else wants it. The platform itself (``session_id`` None)
        stops it for everyone."""
        stream = self.get(name)
        viewers = self.viewers.setdefault(name, {})
        if session_id is not None:
            for key, (_host, sent_to) in list(viewers.items()):
                if _owner(key) == session_id and (not port or sent_to == port):
                    viewers.pop(key)
            if viewers:
                if isinstance(stream, FanOutStream):
                    stream.set_destinations(list(viewers.values()))
                return stream.state
        viewers.clear()
        self.paused.discard(name)
        if stream is self.navcam and self.record_fps:
            return await self._record_only()
        return await stream.stop()

    def bytes_sent(self, name: str, host: str, port: int) -> int:
        """Bytes stream ``name`` sent to ``host:port`` (the MAVLink endpoint charges a ground
        station's video to its address: brasidas.admission.SourceLedger)."""
        stream = self.streams.get(name)
        return stream.bytes_sent_to(host, port) if isinstance(stream, FanOutStream) else 0

    def tap_navcam(self, sink: AccessUnitSink) -> Callable[[], None] | None:
        """``sink`` gets each of the NavCam's encoded access units as it is sent (on the
        streaming thread); returns how to remove it, or None on a platform without a NavCam."""
        navcam = self.navcam
        if navcam is None:
            return None
        navcam.access_unit_sinks.append(sink)
        return lambda: navcam.access_unit_sinks.remove(sink)

    async def record_navcam(self, fps: int) -> StreamState | None:
        """The recorder's own copy (issue 28): while no station watches, the NavCam runs at
        ``fps`` sent nowhere, its encoded frames to the recorder (the same encoder a station's
        copy then uses). None without a NavCam or with ``fps`` 0."""
        self.record_fps = fps
        if self.navcam is None or fps <= 0:
            return None
        if self.viewers.get("navcam"):
            return self.navcam.state
        return await self._record_only()

    async def _record_only(self) -> StreamState:
        assert self.navcam is not None
        self.navcam.set_destinations([])
        self.navcam.set_framerate(min(self.record_fps, self.navcam.settings.camera_framerate))
        return await self.navcam.start()

    def _follow_policy(self) -> None:
        """The NavCam at the framerate of the current mode (a station watches)."""
        if self.navcam is not None and self.navcam.settings.framerate != self.framerate.current:
            self.navcam.set_framerate(self.framerate.current)

    def set_framerate(self, name: str, raw: Any) -> int:
        """10.5: the framerate of a video stream in the current mode; ValueError if invalid."""
        try:
            stream = self.get(name)
        except KeyError as err:
            raise ValueError(err.args[0]) from None
        if not isinstance(stream, VideoOut):
            raise ValueError(f"stream '{name}' is not a video stream")
        if stream is self.navcam:
            fps = self.framerate.set_current(raw)
        else:
            fps = parse_framerate(raw, stream.settings.camera_framerate)
        stream.set_framerate(fps)
        return fps

    # ------------------------------------------------------------------ signaling methods

    async def rpc_start_stream(
        self, call: CallContext, name: str, host: str = "", port: int = 0, copy: bool = False
    ) -> dict[str, Any]:
        session: Session | None = call.session
        session_id = session.session_id if session is not None else None
        try:
            host = check_host(host or _peer_host(session))
        except PayloadError as err:
            raise RpcError(INVALID_PARAMS, f"invalid params: {err}") from None
        refusal = self.destination_refusal(host, session)
        if refusal is not None:
            raise RpcError(INVALID_PARAMS, f"invalid params: {refusal}")
        if port and not 1 <= port <= 65535:
            raise RpcError(INVALID_PARAMS, "invalid params: port must be 1-65535")
        try:
            await self.start_stream(
                self._rpc_name(name), host, port, session_id=session_id, copy=bool(copy)
            )
        except ValueError as err:
            raise RpcError(INVALID_PARAMS, f"invalid params: {err}") from None
        return self.streams[name].describe()

    async def rpc_pause_stream(self, call: CallContext, name: str) -> dict[str, Any]:
        await self.pause_stream(self._rpc_name(name))
        return self.streams[name].describe()

    async def rpc_stop_stream(self, call: CallContext, name: str, port: int = 0) -> dict[str, Any]:
        session: Session | None = call.session
        await self.stop_stream(
            self._rpc_name(name), session_id=session.session_id if session else None, port=port
        )
        return self.streams[name].describe()

    async def rpc_list_streams(self, call: CallContext) -> list[dict[str, Any]]:
        return self.describe_streams()

    def _rpc_name(self, name: str) -> str:
        try:
            return self.get(name).name
        except KeyError as err:
            raise RpcError(INVALID_PARAMS, f"invalid params: {err.args[0]}") from None

    def describe_streams(self) -> list[dict[str, Any]]:
        return [stream.describe() for stream in self.streams.values()]

    def nav_camera(self) -> dict[str, Any]:
        assert self.navcam is not None
        info = self.navcam.describe()
        info["destination"] = self.navcam.destination() if info["state"] != "idle" else None
        info["framerates"] = dict(self.framerate.rates)
        return info


COPIES_MAX = 4
"""Extra copies of one stream a station may have (``view`` and ffplay beside the console)."""
COPY_MARK = "#"
"""Joins a session id and a port: the key of a session's extra copy of a stream."""


def _owner(key: str | None) -> str | None:
    """The session a viewer key belongs to (its extra copies carry ``#port``)."""
    return key.split(COPY_MARK, 1)[0] if key is not None else None


def host_from_payload(payload: str, default: str = "") -> str:
    """10.1's payload: ``host=ADDR``, or the seed's bare address; empty: ``default``."""
    values = parse_payload(payload)
    host = values.get("host", "")
    if "host" not in values and len(values) == 1 and next(iter(values.values())) == "":
        host = next(iter(values))  # the seed's bare "host address" payload
    host = host or default
    if not host:
        raise PayloadError("expected the station's address, e.g. host=10.0.0.2")
    return check_host(host)


def check_host(host: str) -> str:
    """A literal IP address or a plausible host name; PayloadError otherwise."""
    host = host.strip()
    try:
        return str(ipaddress.ip_address(host))
    except ValueError:
        pass
    if not _HOSTNAME.match(host):
        raise PayloadError(f"'{host}' is not an IP address or host name")
    return host


def unroutable(host: str) -> str | None:
    """Why datagrams to ``host`` (a literal address) cannot leave, or None: the kernel's route
    lookup, as the sink's first send would make it (a host name is left to the sink)."""
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return None
    family = socket.AF_INET6 if address.version == 6 else socket.AF_INET
    with socket.socket(family, socket.SOCK_DGRAM) as probe:
        try:
            probe.connect((host, 9))  # no datagram is sent: connect only routes
        except OSError as err:
            return f"no route to {host}: {err.strerror or err}"
    return None


def in_destinations(host: str, allowed: tuple[str, ...]) -> bool:
    """``host`` is an address within one of ``allowed`` (addresses or networks)."""
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return False
    return any(address in ipaddress.ip_network(item, strict=False) for item in allowed)


def _summary(states: dict[str, StreamState]) -> CommandResult:
    failed = [name for name, state in states.items() if state is StreamState.FAILED]
    result = {name: state.value for name, state in states.items()}
    if failed:
        return CommandResult(False, f"failed: {', '.join(failed)}", result)
    return CommandResult(True, result=result)


async def _answer(work: Awaitable[CommandResult]) -> CommandResult:
    try:
        return await work
    except Exception as err:
        _LOGGER.exception("media command failed")
        return CommandResult(False, f"internal error: {err}")


def _peer_host(session: Session | None) -> str:
    """The calling station's address (IPv4-mapped IPv6 unwrapped); empty without a session."""
    if session is None:
        return ""
    return str(session.peer_host).removeprefix("::ffff:")


async def _awaited(work: Awaitable[Any]) -> None:
    await work


async def async_setup(ctx: PlatformContext) -> None:
    service = MediaService(ctx)
    ctx.media = service
    ctx.capabilities.register("streams", service.describe_streams)
    if service.navcam is not None:
        ctx.capabilities.register("nav_camera", service.nav_camera)
    for name in ("start_stream", "stop_stream", "list_streams"):
        ctx.rpc.add(name, getattr(service, f"rpc_{name}"))
    # Pausing affects every viewer: a control method (platformd.authority).
    ctx.rpc.add("pause_stream", ctx.authority.guard("pause_stream", service.rpc_pause_stream))
    ctx.supervisor.start(service)
