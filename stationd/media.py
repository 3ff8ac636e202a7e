"""Station side of the media streams (R-11, Stream Display ch. 11 §4.1).

Local API (CLI, browser console): ``stream_start(platform_id, stream, host, port)``,
``stream_pause``, ``stream_stop`` and ``streams`` ask the platform over its session;
``receive(platform_id, stream, sink)`` also runs a receive pipeline in the daemon (a free
UDP port, the platform asked to send there): video with its per-frame latency, or the
platform's microphone on the station's speaker; ``receivers`` reports them. ``talk`` sends the
station's microphone to the platform's speaker. All of a platform's pipelines stop when its
connection ends.

A platform stream also plays in stock tools. GStreamer (the seed's Annex A habit)::

    gst-launch-1.0 udpsrc port=5600 \\
        caps="application/x-rtp,media=video,clock-rate=90000,encoding-name=H264,payload=96" \\
        ! rtph264depay ! avdec_h264 ! videoconvert ! autovideosink sync=false

ffplay or VLC open the SDP of :func:`sdp_text` (``brasidas-station view ID --sdp FILE``)::

    ffplay -protocol_whitelist file,udp,rtp -fflags nobuffer -flags low_delay navcam.sdp
    vlc navcam.sdp
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import logging
import socket
from typing import Any

from brasidas import topics
from brasidas.actor import Actor, wait_forever
from brasidas.codecs.jsonrpc import INVALID_PARAMS, CallContext, RpcError
from brasidas.media.audio import AudioIn, AudioOut, AudioSettings
from brasidas.media.gst import NTP64_EXT_ID, NTP64_URI, MediaError
from brasidas.media.pipeline import PipelineStream, StreamState
from brasidas.media.video import PAYLOAD_TYPE, VideoIn
from brasidas.messages import PlatformLink
from stationd.context import StationContext

_LOGGER = logging.getLogger(__name__)

GST_LAUNCH_RECEIVER = (
    "gst-launch-1.0 udpsrc port={port} "
    'caps="application/x-rtp,media=video,clock-rate=90000,encoding-name=H264,payload=96" '
    "! rtph264depay ! avdec_h264 ! videoconvert ! autovideosink sync=false"
)
"""The stock receiver command (documented and tested)."""


def sdp_text(
    port: int,
    *,
    listen_host: str = "0.0.0.0",
    name: str = "Brasidas NavCam",
    platform_host: str = "0.0.0.0",
) -> str:
    """An SDP description of a platform H.264 stream arriving on ``port`` (ffplay, VLC)."""
    family = "IP6" if ":" in listen_host else "IP4"
    origin_family = "IP6" if ":" in platform_host else "IP4"
    lines = [
        "v=0",
        f"o=- 0 0 IN {origin_family} {platform_host}",
        f"s={name}",
        f"c=IN {family} {listen_host}",
        "t=0 0",
        f"m=video {port} RTP/AVP {PAYLOAD_TYPE}",
        f"a=rtpmap:{PAYLOAD_TYPE} H264/90000",
        # Constrained baseline; SPS/PPS travel in-band (config-interval=-1).
        f"a=fmtp:{PAYLOAD_TYPE} packetization-mode=1;profile-level-id=42e01f",
        f"a=extmap:{NTP64_EXT_ID} {NTP64_URI}",
        "a=recvonly",
    ]
    return "\r\n".join(lines) + "\r\n"


def free_udp_port(host: str = "0.0.0.0") -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind((host, 0))
        return int(sock.getsockname()[1])


def receive_host(platform_host: str) -> str:
    """Listen on loopback for a platform on loopback (tests, demo), else on every interface."""
    try:
        loopback = ipaddress.ip_address(platform_host).is_loopback
    except ValueError:
        loopback = platform_host == "localhost"
    return "127.0.0.1" if loopback else "0.0.0.0"


class StationMedia(Actor):
    """Stream control through platform sessions; receive pipelines run by the daemon."""

    name = "media"

    def __init__(self, ctx: StationContext) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self.receivers: dict[tuple[str, str], PipelineStream] = {}
        """Receive pipelines (and the talk sender) by (platform id, stream)."""
        self._group: asyncio.TaskGroup | None = None

    async def run(self) -> None:
        self.subscribe(topics.PLATFORM_DISCONNECTED, self._on_disconnected)
        async with asyncio.TaskGroup() as group:
            self._group = group
            try:
                await wait_forever()
            finally:
                self._group = None

    async def async_stop(self) -> None:
        receivers = list(self.receivers.values())
        self.receivers.clear()
        await asyncio.gather(*(r.stop() for r in receivers), return_exceptions=True)

    def _on_disconnected(self, link: PlatformLink) -> None:
        for key in [key for key in self.receivers if key[0] == link.platform_id]:
            if self._group is not None:
                self._group.create_task(self._stop_receiver(key), name=f"media:stop:{key[1]}")

    async def _stop_receiver(self, key: tuple[str, str]) -> None:
        # Stays listed until stopped: a daemon stopping meanwhile (async_stop) stops it too,
        # rather than dropping a pipeline that is still PLAYING.
        receiver = self.receivers.get(key)
        if receiver is None:
            return
        await receiver.stop()
        if self.receivers.get(key) is receiver:
            del self.receivers[key]

    # ------------------------------------------------------------------ local API

    async def api_stream_start(
        self,
        call: CallContext,
        platform_id: str,
        stream: str = "navcam",
        host: str = "",
        port: int = 0,
    ) -> dict[str, Any]:
        connection = await self.ctx.connection(platform_id)
        params: dict[str, Any] = {"name": stream}
        if host:
            params["host"] = host
        if port:
            # A consumer of its own (``view``, ffplay): one more copy, beside the console's.
            params.update(port=port, copy=True)
        answer: dict[str, Any] = await connection.call("start_stream", **params)
        return answer

    async def api_stream_pause(
        self, call: CallContext, platform_id: str, stream: str = "navcam"
    ) -> dict[str, Any]:
        connection = await self.ctx.connection(platform_id)
        answer: dict[str, Any] = await connection.call("pause_stream", name=stream)
        return answer

    async def api_stream_stop(
        self, call: CallContext, platform_id: str, stream: str = "navcam", port: int = 0
    ) -> dict[str, Any]:
        """Stop this station's copies of ``stream`` (only the one sent to ``port`` if given)."""
        connection = await self.ctx.connection(platform_id)
        params: dict[str, Any] = {"name": stream}
        if port:
            params["port"] = port
        answer: dict[str, Any] = await connection.call("stop_stream", **params)
        return answer

    async def api_streams(self, call: CallContext, platform_id: str) -> list[dict[str, Any]]:
        connection = await self.ctx.connection(platform_id)
        answer: list[dict[str, Any]] = await connection.call("list_streams")
        return answer

    async def api_receive(
        self, call: CallContext, platform_id: str, stream: str = "navcam", sink: str = "fakesink"
    ) -> dict[str, Any]:
        """Receive ``stream`` here (a free port) and ask the platform to send it.

        Video streams decode into ``sink`` (fakesink, or a window: "auto"); the platform's
        microphone (``audio_out``) plays on the station's speaker ("auto") or fakesink.
        """
        if sink not in ("fakesink", "auto", "autovideosink", "autoaudiosink"):
            raise RpcError(INVALID_PARAMS, "invalid params: sink must be fakesink or auto")
        connection = await self.ctx.connection(platform_id)
        kinds = {s.get("name"): s.get("kind") for s in await connection.call("list_streams")}
        kind = kinds.get(stream)
        if kind not in ("video_out", "payload_camera", "audio_out"):
            known = ", ".join(str(n) for n, k in kinds.items() if k != "audio_in") or "none"
            raise RpcError(INVALID_PARAMS, f"no stream named '{stream}' to receive ({known})")
        key = (platform_id, stream)
        old = self.receivers.pop(key, None)
        if old is not None:
            await old.stop()
        host = receive_host(connection.platform_host)
        name, port = f"{platform_id}/{stream}", free_udp_port(host)
        receiver: PipelineStream
        if kind == "audio_out":
            receiver = AudioIn(
                name,
                host=host,
                port=port,
                device=self.ctx.config.media.speaker_device,
                sink="fakesink" if sink == "fakesink" else "",
            )
        else:
            video_sink = "fakesink" if sink == "fakesink" else "autovideosink"
            receiver = VideoIn(name, host=host, port=port, sink=video_sink)
        self.receivers[key] = receiver
        if await receiver.start() is StreamState.FAILED:
            self.receivers.pop(key, None)
            await receiver.stop()
            raise RpcError(INVALID_PARAMS, f"cannot receive: {receiver.reason}")
        try:
            started = await connection.call("start_stream", name=stream, port=port)
        except (RpcError, MediaError):
            self.receivers.pop(key, None)
            await receiver.stop()
            raise
        if isinstance(receiver, VideoIn) and isinstance(started, dict):
            rtcp_port = started.get("rtcp_port")
            receiver.set_feedback(
                connection.platform_host, rtcp_port if isinstance(rtcp_port, int) else 0
            )
            await receiver.follow_sender(started)
        if isinstance(receiver, VideoIn) and stream == "navcam":
            connection.video_latency = receiver.recent_latency_ms
        return {"platform_id": platform_id, **receiver.describe()}

    async def api_talk(
        self, call: CallContext, platform_id: str, on: bool = True, test_tone: bool = False
    ) -> dict[str, Any]:
        """The station's microphone (or a test tone) to the platform's speaker, or stop it."""
        key = (platform_id, "talk")
        old = self.receivers.pop(key, None)
        if old is not None:
            await old.stop()
        connection = await self.ctx.connection(platform_id)
        if not on:
            with contextlib.suppress(RpcError, ConnectionError):
                await connection.call("stop_stream", name="audio_in")
            return {"platform_id": platform_id, "state": "idle"}
        listening: dict[str, Any] = await connection.call("start_stream", name="audio_in")
        host = str(listening.get("host") or "")
        if host in ("", "0.0.0.0", "::"):
            host = connection.platform_host
        microphone = AudioOut(
            f"{platform_id}/talk",
            AudioSettings(
                device=self.ctx.config.media.microphone_device,
                test_source=test_tone,
                host=host,
                port=int(listening["port"]),
            ),
        )
        self.receivers[key] = microphone
        if await microphone.start() is StreamState.FAILED:
            self.receivers.pop(key, None)
            await microphone.stop()
            raise RpcError(INVALID_PARAMS, f"cannot send audio: {microphone.reason}")
        return {"platform_id": platform_id, **microphone.describe()}

    async def api_stop_receive(
        self, call: CallContext, platform_id: str, stream: str = "navcam"
    ) -> bool:
        receiver = self.receivers.pop((platform_id, stream), None)
        if receiver is None:
            return False
        await receiver.stop()
        connection = self.ctx.connections.get(platform_id)
        if connection is not None:
            with contextlib.suppress(RpcError, ConnectionError):
                await connection.call("stop_stream", name=stream)
        return True

    async def api_receivers(self, call: CallContext) -> list[dict[str, Any]]:
        return [
            {"platform_id": platform_id, "stream": stream, **receiver.describe()}
            for (platform_id, stream), receiver in self.receivers.items()
        ]


async def async_setup(ctx: StationContext) -> None:
    media = StationMedia(ctx)
    for name in (
        "stream_start",
        "stream_pause",
        "stream_stop",
        "streams",
        "receive",
        "stop_receive",
        "receivers",
        "talk",
    ):
        ctx.api.add(name, getattr(media, f"api_{name}"), session_required=False)
    ctx.supervisor.start(media)
