"""H.264 over RTP: the NavCam sender (the seed's PiGstVideoOut) and the station's receiver.

Sender: camera (V4L2, raw or MJPEG) or a live test source with motion and a clock overlay
→ capture stamp → ``videorate`` (the framerate changes live) → H.264 encoder (first found of
:data:`ENCODERS`; constrained baseline, one slice per frame, a keyframe every second) →
``rtph264pay config-interval=-1 mtu=1200`` with the RFC 6051 NTP-64 header extension on every
packet → ``udpsink sync=false``.

Receiver: ``udpsrc`` with explicit caps → optional jitter buffer → ``rtph264depay`` →
``avdec_h264`` → sink, with the glass-to-glass latency of each decoded frame read from the
header extension.
"""

from __future__ import annotations

import collections
import statistics
import threading
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from functools import partial
from typing import Any

from brasidas.media.bitrate import (
    DRAIN_PAUSE_S,
    STALE_RETRANSMISSION_S,
    THIN_AFTER_COLLAPSE_S,
    BitrateController,
    FrameBudget,
    ResolutionChoice,
    TransportReport,
    frame_thinning,
)
from brasidas.media.fanout import Destinations, FanOutStream
from brasidas.media.gst import (
    NTP64_EXT_ID,
    NTP64_URI,
    NTP_UNIX_OFFSET_NS,
    TWCC_EXT_ID,
    TWCC_URI,
    MediaError,
    caps,
    capture_age_ms,
    gst,
    has_element,
    link_all,
    make,
    ntp_caps,
    set_prop,
    stamp_capture_time,
)
from brasidas.media.keyframe_now import KeyframeNow
from brasidas.media.keyframes import (
    KEYFRAME_INTERVAL_S,
    REFRESH_KEYFRAME_INTERVAL_S,
    KeyframeClock,
)
from brasidas.media.pipeline import PipelineStream, StreamState
from brasidas.media.repair import (
    FEC_PAYLOAD_TYPE,
    FEC_RTX_PAYLOAD_TYPE,
    RTX_PAYLOAD_TYPE,
    TAIL_COPY_MAX_FPS,
    FeedbackSocket,
    LossyLink,
    RepairReceiver,
    TailCopies,
    add_repair_receiver,
    add_repair_sender,
    fec_percentage,
)
from brasidas.media.streaming_caps import StreamingThreadCaps
from brasidas.media.twcc import (
    RTCP_RTPFB,
    TWCC_FMT,
    QueueDetector,
    QueueOveruse,
    SendHistory,
    transport_seq,
)

ENCODERS: tuple[str, ...] = ("v4l2h264enc", "omxh264enc", "x264enc", "openh264enc")
"""Hardware first (current Raspberry Pi, old Raspbian), then software; first found wins."""
PAYLOAD_TYPE = 96
MIN_BITRATE_KBPS = 150
RTP_VIDEO_CAPS = (
    "application/x-rtp,media=video,clock-rate=90000,encoding-name=H264,"
    f"payload={PAYLOAD_TYPE},extmap-{NTP64_EXT_ID}=(string){NTP64_URI},"
    f"extmap-{TWCC_EXT_ID}=(string){TWCC_URI}"
)
"""What a receiver must tell ``udpsrc``: plain RTP carries no SDP."""
TAP_QUEUE_BUFFERS = 30
VIDEO_DSCP = 34
"""AF41, interactive video: below the velocity stream's EF on a link that honours DSCP."""
INTRA_REFRESH_ENCODERS = ("x264enc",)
"""Encoders whose GStreamer element exposes periodic intra refresh. (openh264enc does not;
the Pi's v4l2h264enc and omxh264enc were not available here to verify a control.)"""
X264_VBV_MS = 200
"""x264's rate-control buffer: how far one frame may exceed the bitrate's share (measured at
a 2 Mbit/s → 500 kbit/s drop: with 600 ms, the keyframe after it was lost to the link's
queue and the picture froze 0.8-1.1 s; with 200 ms, 0.5-0.6 s)."""
X264_RECOVERY_VBV_MS = 50
"""x264's rate-control buffer from a drain pause until the bitrate is no longer held
(:class:`~brasidas.media.bitrate.FrameBudget`'s window): the keyframe after the pause is then
made at the lowered bitrate's size, not at what the buffer still allowed (measured at the cut
to 450 kbit/s: 5.7 kB at 320x240, 7.5 kB at 640x480 with 200 ms, each ~100 ms of a
500 kbit/s link before the picture could restart; 1.9-2.0 kB with 50 ms, and the frames
after it within the bitrate at once instead of a second's catching up)."""
ENCODER_GOP_S = 10
"""The encoder's own keyframe interval, a backstop only: :class:`KeyframeClock` forces the
keyframes, at the current framerate (the encoders' own settings cannot change while running)."""
"""Access units the encoded tap may hold before its leaky queue drops the oldest."""

AccessUnitSink = Callable[[bytes, bool, int], None]
"""``(annex_b, keyframe, capture_time_ns)`` for each encoded access unit, called on
GStreamer's streaming thread: it must not block (hand the bytes to a queue)."""


def choose_encoder(forced: str = "") -> str:
    """The encoder to use: ``forced`` if given (must exist), else the first available."""
    if forced:
        if forced not in ENCODERS:
            raise MediaError(f"unknown encoder '{forced}' (one of {', '.join(ENCODERS)})")
        if not has_element(forced):
            raise MediaError(f"encoder '{forced}' is not installed")
        return forced
    for name in ENCODERS:
        if has_element(name):
            return name
    raise MediaError(f"no H.264 encoder installed (tried {', '.join(ENCODERS)})")


@dataclass
class VideoSettings(Destinations):
    """What a :class:`VideoOut` sends; change fields, then ``set_framerate``/``restart``."""

    width: int = 640
    height: int = 480
    camera_framerate: int = 30
    """What the source delivers; the sent framerate is at most this."""
    framerate: int = 30
    bitrate_kbps: int = 1500
    """At ``camera_framerate``; lower framerates get a proportional share (same quality)."""
    device: str = "/dev/video0"
    source_format: str = "raw"
    """Camera output: "raw" or "mjpeg"."""
    test_source: bool = False
    """A live ``videotestsrc`` with a clock overlay instead of the camera (--sim)."""
    pattern: str = "ball"
    motion: int = 0
    """``videotestsrc horizontal-speed``: moves patterns such as smpte (bandwidth tests)."""
    encoder: str = ""
    """Force an encoder from :data:`ENCODERS`; empty: the first available."""
    mtu: int = 1200
    repair: bool = True
    """RTCP feedback, retransmission on NACK, keyframes on PLI (:mod:`brasidas.media.repair`)."""
    rtcp_port: int = 0
    """Where receivers send their RTCP feedback (0: a free port, announced as ``rtcp_port``)."""
    intra_refresh: bool = False
    """Periodic intra refresh instead of periodic keyframes, where the encoder has it
    (:data:`INTRA_REFRESH_ENCODERS`): a column of intra blocks sweeps the picture once a
    second, so no frame is a burst many times the others and a loss heals within a second
    without a keyframe. x264 answers a force-key-unit (PLI, the keyframe clock) with a new
    sweep, not an IDR: receivers must decode on (:meth:`VideoIn.follow_sender`)."""
    fec_max_percent: int = 0
    """The most ULPFEC overhead (0 disables FEC): the share follows the reported loss
    (:func:`~brasidas.media.repair.fec_percentage`), within the bitrate."""

    def uses_intra_refresh(self, encoder_name: str) -> bool:
        return self.intra_refresh and encoder_name in INTRA_REFRESH_ENCODERS

    def effective_bitrate_kbps(self) -> int:
        """Bitrate for the current framerate: 5 fps monitoring needs a sixth of 30 fps."""
        share = self.bitrate_kbps * self.framerate / max(1, self.camera_framerate)
        return max(MIN_BITRATE_KBPS, min(self.bitrate_kbps, round(share)))


class VideoOut(FanOutStream[VideoSettings]):
    """Camera → H.264 → RTP/UDP to each station asking (the seed's PiGstVideoOut)."""

    kind = "video_out"

    def __init__(self, name: str, settings: VideoSettings, **kwargs: Any) -> None:
        super().__init__(name, settings, **kwargs)
        self.encoder_name = ""
        self._encoder: Any = None
        self._rate_filter: Any = None
        self.keyframes = KeyframeClock(settings.framerate)
        self.thinning = 1
        """One frame in ``thinning`` goes to the encoder (the link forced the bitrate far down:
        :func:`~brasidas.media.bitrate.frame_thinning`); read by the streaming thread."""
        self._frames_seen = 0
        self.frames_encoded = 0
        """Frames out of the encoder since the stream was made (a receiver's frames shown
        count against these: not against the nominal framerate, which the camera, the
        thinning and a restart all stray from); read by the streaming thread."""
        self.budget = FrameBudget(settings.effective_bitrate_kbps())
        """Frames are skipped, not encoded, while the encoded ones would queue (under the
        keyframes' lock: the streaming thread and the event loop)."""
        self.keyframe_after_pause = False
        self._adapt_lock = threading.Lock()
        """The bitrate adapts on the event loop and on RTCP's thread."""
        self.stale_before = 0
        """Packets sent before the pause (sequence numbers before this) are not sent again
        until ``stale_until``: the picture restarts at the keyframe after it, and their
        retransmissions would queue ahead of it (read by the streaming thread)."""
        self.stale_until = 0.0
        """The first frame after the pause is a keyframe (under the keyframes' lock)."""
        self.reported_jitter_ms = 0.0
        """The newest receiver report's interarrival jitter (a queue building shows here)."""
        self.fec_percent = 0
        """The ULPFEC overhead now (percent of the media packets)."""
        self._keyframes_lock = threading.Lock()
        """The clock is used by the streaming thread, RTCP's thread and the event loop."""
        self._keyframe_now: KeyframeNow | None = None
        """Answers a request with the newest frame encoded again at once (not with intra
        refresh: x264 then answers with a new sweep, not a keyframe)."""
        self._forced_seqnums: collections.deque[int] = collections.deque(maxlen=8)
        """Our own force-key-unit events, told apart from a receiver's request (PLI/FIR)."""
        self.feedback: FeedbackSocket | None = None
        self._tail_copies: TailCopies | None = None
        self.lossy_link = LossyLink()
        """Copies of the frames' last packets at any framerate while the link is lossy."""
        self.bitrate = BitrateController(settings.effective_bitrate_kbps(), MIN_BITRATE_KBPS)
        self._rtpbin: Any = None
        self._rtx_pad: Any = None
        self._rtx_probe: int | None = None
        self._reports_seen: dict[int, int] = {}
        self.resolution = ResolutionChoice()
        """Half the picture's width and height while the bitrate is too low for all of it."""
        self._scale_filter: Any = None
        self._streaming_caps: StreamingThreadCaps | None = None
        """The rate and scale filters' new caps, set by the streaming thread (never from
        another thread inside one of its caps queries: the stream would fail)."""
        self._vbv_ms = X264_VBV_MS
        """x264's rate-control buffer now (:meth:`_follow_recovery_vbv`)."""
        self.retransmit = True
        self.retransmissions_dropped = 0
        self.retransmissions_emptied = 0
        """Packets sent before a drain pause, asked for again after it: sent without their
        media (:func:`emptied_retransmission`), so no receiver waits for them."""
        self._dropped_seen = 0
        """False while the link's queue overflows: retransmissions are dropped (read by the
        streaming thread)."""
        self.transport: TransportReport | None = None
        """The newest window of transport-wide feedback (what arrived, the delay's trend)."""
        self._transport_seen: Any = None
        self.send_history = SendHistory()
        """Each packet's send time and size by its transport-wide number (streaming thread)."""
        self.queue_detector = QueueDetector()
        """The link's queue from each transport feedback, packet by packet (RTCP's thread)."""
        self._queue_overuse: QueueOveruse | None = None
        """Each receiver's highest sequence number in its last report used (new ones only)."""
        self.access_unit_sinks: list[AccessUnitSink] = []
        """Who gets the encoded stream (the recorder): a tee after the encoder feeds them,
        as sent, never a second encoder. Set before the pipeline is built."""

    def describe(self) -> dict[str, Any]:
        s = self.settings
        return {
            **super().describe(),
            "width": s.width,
            "height": s.height,
            "sent_size": list(self.resolution.size(s.width, s.height)),
            "framerate": s.framerate,
            "codec": "H264",
            "encoder": self.encoder_name or None,
            "bitrate_kbps": self.current_bitrate_kbps(),
            "bitrate_ceiling_kbps": s.effective_bitrate_kbps(),
            "reported_loss": round(self.bitrate.loss, 3),
            "reported_jitter_ms": self.reported_jitter_ms,
            "transport": vars(self.transport) if self.transport is not None else None,
            "overuses": self.bitrate.overuses,
            "transport_silences": self.bitrate.silences,
            "transport_queue_stalls": self.bitrate.queue_stalls,
            "reports_across_cuts": self.bitrate.cut_reports,
            "queue_ms": round(self.bitrate.queue_ms, 1),
            "transport_feedback": {
                **vars(self.queue_detector.counters),
                "queue_ms": round(self.queue_detector.queue_ms, 1),
                "capacity_kbps": round(self.queue_detector.capacity_kbps),
                "overuses": self.bitrate.queue_overuses,
            },
            "retransmissions_dropped": self.retransmissions_dropped,
            "retransmissions_emptied": self.retransmissions_emptied,
            "drain_pauses": self.bitrate.pauses,
            "frames_skipped": self.budget.skipped,
            "keyframes_after_pause": self.keyframes.counters.resumed,
            **self.retransmissions(),
            "rtp_caps": RTP_VIDEO_CAPS,
            "rtcp_port": self.feedback.port if self.feedback is not None else None,
            "keyframe_interval_frames": self.keyframes.interval_frames,
            "intra_refresh": self.encoder_name != "" and s.uses_intra_refresh(self.encoder_name),
            "fec_percent": self.fec_percent,
            "framerate_sent": s.framerate // self.thinning,
            "frames_encoded": self.frames_encoded,
            "fec_max_percent": s.fec_max_percent,
            "tail_copies": self.tail_copies_sent(),
            "keyframes_requested": self.keyframes.counters.requested,
            "keyframe_requests_deferred": self.keyframes.counters.deferred,
            "keyframes_at_once": self.keyframes_at_once,
        }

    def tail_copies_sent(self) -> int:
        """Frames' last packets sent twice (a low framerate's: :class:`TailCopies`)."""
        return self._tail_copies.sent if self._tail_copies is not None else 0

    def current_bitrate_kbps(self) -> int:
        return self.bitrate.effective_kbps(self.settings.effective_bitrate_kbps())

    def retransmissions(self) -> dict[str, int]:
        """NACKed packets asked for and sent again (the sender's side of repair)."""
        rtx = self.pipeline.get_by_name("rtxsend") if self.pipeline is not None else None
        if rtx is None:
            return {}
        return {
            "retransmission_requests": int(rtx.get_property("num-rtx-requests")),
            "retransmitted": int(rtx.get_property("num-rtx-packets")),
        }

    def adapt_bitrate(self, now: float) -> int | None:
        """The encoder's bitrate from the receivers' newest reports
        (:class:`BitrateController`); the new bitrate when it changed. The event loop calls it
        every :data:`~brasidas.media.bitrate.TRANSPORT_POLL_S`, RTCP's thread at each transport
        feedback (a capacity drop seen without waiting for the loop)."""
        with self._adapt_lock:
            if self._rtpbin is None or self._encoder is None:
                return None
            kbps = self._adapt_bitrate(now)
            self._follow_lossy_link(now)
            return kbps

    def _follow_lossy_link(self, now: float) -> None:
        """Copy the frames' last packets at any framerate while the link is lossy (the share
        of packets the receivers asked for again; :class:`LossyLink`)."""
        rtx = self._rtpbin.get_by_name("rtxsend") if self._rtpbin is not None else None
        pay = self.pipeline.get_by_name("pay") if self.pipeline is not None else None
        if rtx is None or pay is None or self._tail_copies is None:
            return
        was = self.lossy_link.on
        requests = int(rtx.get_property("num-rtx-requests"))
        if self.lossy_link.update(requests, int(pay.get_property("seqnum")), now) != was:
            self._tail_copies.follow()

    def _adapt_bitrate(self, now: float) -> int | None:
        ceiling = self.settings.effective_bitrate_kbps()
        loss = self._newest_reported_loss(now)
        transport = self._newest_transport_report()
        paused_at = self.bitrate.paused_at
        queued, self._queue_overuse = self._queue_overuse, None
        fell = None
        if queued is not None and now - queued.at < QUEUE_OVERUSE_FRESH_S:
            fell = self.bitrate.on_queue(
                queued.sent_kbps,
                queued.capacity_kbps,
                ceiling,
                now,
                sent_at=queued.newest_sent_at,
            )
        if transport is not None:
            fell = self.bitrate.on_transport(transport, ceiling, now) or fell
        else:
            fell = self.bitrate.confirm_pending(ceiling, now) or fell
        if self.bitrate.paused_at != paused_at:
            # The queue overflows: no frame until it drained, then a keyframe (the frames
            # sent meanwhile lost packets: the receivers wait for one).
            with self._keyframes_lock:
                self.keyframe_after_pause = True
                self.budget.pause(DRAIN_PAUSE_S, now)
            pay = self.pipeline.get_by_name("pay") if self.pipeline is not None else None
            if pay is not None:
                self.stale_before = (int(pay.get_property("seqnum")) + 1) & 0xFFFF
                self.stale_until = now + STALE_RETRANSMISSION_S
        kbps = self.bitrate.update(loss, ceiling, now) or fell
        retransmit = not self.bitrate.retransmissions_paused(now)
        if retransmit and not self.retransmit and self.retransmissions_dropped > self._dropped_seen:
            # The queue drained: what it dropped was not sent again, so the receivers wait
            # for a keyframe; make it now, on the empty link, not after their timeout.
            self.request_keyframe()
        if not retransmit and self.retransmit:
            self._dropped_seen = self.retransmissions_dropped
        self.retransmit = retransmit
        # The probe also drops the retransmissions of what was sent before a drain pause.
        self._drop_retransmissions(not retransmit or now < self.stale_until)
        # Right after a capacity drop FEC would only add to the queue that drops the packets:
        # it is for a link's random loss (which, by loss alone, is any loss but a collapse).
        collapsed = self.bitrate.collapsed_at
        congested = collapsed is not None and now - collapsed < THIN_AFTER_COLLAPSE_S
        fec = 0 if congested else fec_percentage(self.bitrate.loss, self.settings.fec_max_percent)
        fec_changed = fec != self.fec_percent
        if fec_changed:
            self.fec_percent = fec
            encoder = self._rtpbin.get_by_name("fecenc")
            if encoder is not None:
                encoder.set_property("percentage", fec)
        thinning = (
            frame_thinning(
                self.settings.framerate,
                self.current_bitrate_kbps(),
                self.settings.effective_bitrate_kbps(),
            )
            if congested
            else 1
        )
        if thinning != self.thinning:
            self.thinning = thinning
            with self._keyframes_lock:  # its interval counts the frames encoded
                self.keyframes.set_framerate(max(1, self.settings.framerate // thinning))
        with self._keyframes_lock:  # a periodic keyframe is queued, not lost, while congested
            self.keyframes.congested = congested
        if kbps is not None or fec_changed:
            _set_bitrate(self._encoder, self.encoder_name, self.media_bitrate_kbps())
        with self._keyframes_lock:
            self.budget.set_rate(self.current_bitrate_kbps(), now)
        self._follow_recovery_vbv(now)
        self._follow_resolution(now)
        return kbps

    def _follow_recovery_vbv(self, now: float) -> None:
        """x264's short rate-control buffer while the bitrate is held after a drain pause
        (:data:`X264_RECOVERY_VBV_MS`), its usual one after; applied live (x264 reconfigures
        at its next frame, before the keyframe the pause ends with)."""
        if self.encoder_name != "x264enc" or self._encoder is None:
            return
        vbv_ms = X264_RECOVERY_VBV_MS if now < self.budget.enforced_until else X264_VBV_MS
        if vbv_ms != self._vbv_ms:
            self._vbv_ms = vbv_ms
            self._encoder.set_property("vbv-buf-capacity", vbv_ms)

    def _follow_resolution(self, now: float) -> None:
        """Halve the picture's size when the bitrate cannot carry all of it, and back (the
        encoder restarts on the new size with a keyframe and its new SPS; decoders follow)."""
        s = self.settings
        paused = self.budget.paused_until > now
        scale_filter, streaming_caps = self._scale_filter, self._streaming_caps
        if scale_filter is None or streaming_caps is None:
            return
        if self.bitrate.settling(now) and not paused:
            # Not while a queue drains after a cut: the new size costs a keyframe, and the
            # receivers are waiting for one already (measured: a freeze at the drop twice as
            # long). But during the pause: the keyframe after it is made at the new size (a
            # quarter of the pixels: a third of the bytes to cross the slow link).
            return
        # At the full framerate's bits per pixel, before any thinning: fewer frames and fewer
        # pixels both, on a link that forced the bitrate that far down.
        if not self.resolution.update(
            self.current_bitrate_kbps(), s.width, s.height, s.framerate, now
        ):
            return
        width, height = self.resolution.size(s.width, s.height)
        streaming_caps.want(scale_filter, f"video/x-raw,width={width},height={height}")

    def media_bitrate_kbps(self) -> int:
        """The encoder's share of the bitrate: the FEC packets are carried within it."""
        return max(
            MIN_BITRATE_KBPS, round(self.current_bitrate_kbps() * 100 / (100 + self.fec_percent))
        )

    def _newest_transport_report(self) -> TransportReport | None:
        """The sender's rtpsession's newest transport-wide feedback window, if new."""
        session = self._rtpbin.emit("get-session", 0)
        stats = session.get_property("twcc-stats") if session is not None else None
        if stats is None or not stats.has_field("bitrate-recv"):
            return None
        _, sent = stats.get_uint("bitrate-sent")
        _, received = stats.get_uint("bitrate-recv")
        _, trend_ns = stats.get_int64("avg-delta-of-delta")
        seen = (sent, received, trend_ns)
        if seen == self._transport_seen or not sent:
            return None
        self._transport_seen = seen
        self.transport = TransportReport(
            sent_kbps=round(sent / 1000, 1),
            received_kbps=round(received / 1000, 1),
            delay_trend_ms=round(trend_ns / 1e6, 3),
            packet_bytes=self.settings.mtu,
        )
        return self.transport

    def _newest_reported_loss(self, now: float) -> float | None:
        """The worst fraction lost among the receivers' reports new since the last look."""
        session = self._rtpbin.emit("get-internal-session", 0)
        stats = session.get_property("stats") if session is not None else None
        if stats is None:
            return None
        worst: float | None = None
        for source in stats.get_value("source-stats") or []:
            ok, have_rb = source.get_boolean("have-rb")
            if not ok or not have_rb:
                continue
            _, ssrc = source.get_uint("ssrc")
            _, highest = source.get_uint("rb-exthighestseq")
            if self._reports_seen.get(ssrc) == highest:
                continue
            self._reports_seen[ssrc] = highest
            _, lost = source.get_int("rb-packetslost")
            self.bitrate.note_report(ssrc, highest, lost, now)
            _, fraction = source.get_uint("rb-fractionlost")
            worst = max(worst or 0.0, fraction / 256)
            _, jitter = source.get_uint("rb-jitter")
            self.reported_jitter_ms = round(jitter / 90, 1)  # 90 kHz RTP clock
        return worst

    def _drop_retransmissions(self, drop: bool) -> None:
        """The bitrate's adaptation (event loop or RTCP's thread, under its lock): the probe that
        drops retransmissions is on the retransmitter's pad only while any are dropped (every
        packet passes there: a probe that only looked would take the GIL on the streaming
        thread for each, a tail on the frames' latency)."""
        if drop and self._rtx_probe is None and self._rtx_pad is not None:
            self._rtx_probe = self._rtx_pad.add_probe(
                gst().PadProbeType.BUFFER, _retransmission_probe, weakref.ref(self)
            )
        elif not drop and self._rtx_probe is not None and self._rtx_pad is not None:
            self._rtx_pad.remove_probe(self._rtx_probe)
            self._rtx_probe = None

    def request_keyframe(self) -> None:
        """Make the next frame a keyframe (rate-limited: deferred, never dropped); any thread.
        Answered at once by the newest frame encoded again, unless the link is congested (the
        copy would add to its queue: the next frame answers, as before)."""
        now = time.monotonic()
        with self._keyframes_lock:
            self.keyframes.request(now)
            at_once = (
                self.keyframes.answers_now(now)
                and not self.keyframes.congested
                and not self.keyframe_after_pause
                and self.budget.paused_until <= now
                and self.thinning == 1
            )
        keyframe_now = self._keyframe_now
        if at_once and keyframe_now is not None:
            keyframe_now.ask()

    @property
    def keyframes_at_once(self) -> int:
        """Requests answered at once by the newest frame encoded again (this pipeline's)."""
        return self._keyframe_now.injected if self._keyframe_now is not None else 0

    def set_framerate(self, fps: int) -> None:
        """Change the sent framerate; applied live (keyframe interval follows). Event loop."""
        s = self.settings
        if not 1 <= fps <= s.camera_framerate:
            raise ValueError(f"framerate must be 1-{s.camera_framerate} fps, not {fps}")
        s.framerate = fps
        with self._keyframes_lock:
            self.keyframes.set_framerate(fps)
        if self._tail_copies is not None:
            self._tail_copies.follow()
        streaming_caps = self._streaming_caps
        if (
            self._encoder is not None
            and self._rate_filter is not None
            and streaming_caps is not None
        ):
            _set_bitrate(self._encoder, self.encoder_name, self.media_bitrate_kbps())
            if s.uses_intra_refresh(self.encoder_name):
                # x264 reads it when the new caps restart it: one refresh wave a second.
                _set_keyframe_interval(self._encoder, self.encoder_name, fps)
            # New caps renegotiate downstream: the encoder restarts with the new rate.
            streaming_caps.want(self._rate_filter, f"video/x-raw,framerate={fps}/1")

    # ------------------------------------------------------------------ pipeline

    def build(self) -> Any:
        Gst = gst()
        s = self.settings
        encoder_name = choose_encoder(s.encoder)
        pipeline = Gst.Pipeline.new(f"{self.name}-out")
        source_chain = self._source_elements()
        stamp = make("identity", "stamp", signal_handoffs=True, silent=True)
        stamp.connect("handoff", stamp_capture_time, ntp_caps())
        overlays: list[Any] = []
        if s.test_source:
            # The wall clock on the test picture: redrawn once a second. (A running time
            # redrawn every frame, after the capture stamp, cost 0.5 ms a frame at the median
            # and up to 9 under load: transport latency that a real camera does not have.)
            overlays = [
                make("clockoverlay", time_format="%H:%M:%S", halignment="left", valignment="top")
            ]
        rate = make("videorate", drop_only=True)
        rate_filter = make(
            "capsfilter", "rate", caps=caps(f"video/x-raw,framerate={s.framerate}/1")
        )
        width, height = self.resolution.size(s.width, s.height)
        scale = make("videoscale")
        scale_filter = make(
            "capsfilter", "scale", caps=caps(f"video/x-raw,width={width},height={height}")
        )
        convert = make("videoconvert")
        encoder = make(encoder_name, "encoder")
        _configure_encoder(encoder, encoder_name, s)
        self._vbv_ms = X264_VBV_MS  # as configured; a held bitrate's shorter one follows
        _set_bitrate(encoder, encoder_name, self.media_bitrate_kbps())  # as adapted so far
        h264_caps = _h264_caps(encoder_name)
        if s.uses_intra_refresh(encoder_name):
            # Byte-stream: x264 then repeats SPS/PPS at the start of every refresh wave, so a
            # receiver that missed the first IDR (there is no other) can start within a second.
            h264_caps += ",stream-format=byte-stream"
        h264_filter = make("capsfilter", caps=caps(h264_caps))
        pay = make(
            "rtph264pay", "pay", config_interval=-1, mtu=s.mtu, pt=PAYLOAD_TYPE, aggregate_mode=0
        )
        extension = make("rtphdrextntp64", every_packet=True)
        extension.set_id(NTP64_EXT_ID)
        pay.emit("add-extension", extension)
        if s.repair:
            transport_wide = make("rtphdrexttwcc")
            transport_wide.set_id(TWCC_EXT_ID)
            pay.emit("add-extension", transport_wide)
        sink = self.make_sink()
        tap: list[Any] = []
        if self.access_unit_sinks:
            # No queue on the sending branch: the tee pushes to it first, on the encoder's
            # thread as before (no added hop, no added latency); the tap's leaky queue after.
            tap = [make("tee", "encoded")]
        chain = [
            *source_chain,
            stamp,
            *overlays,
            rate,
            rate_filter,
            scale,
            scale_filter,
            convert,
            encoder,
            h264_filter,
            *tap,
            pay,
        ]
        for element in (*chain, sink):
            pipeline.add(element)
        link_all(*chain)
        if s.repair:
            if self.feedback is None:
                # Bound once and kept across rebuilds: receivers were told this port.
                self.feedback = FeedbackSocket(port=s.rtcp_port)
            self._rtpbin = add_repair_sender(pipeline, pay, sink, self.feedback)
            session = self._rtpbin.emit("get-session", 0)
            if session is not None and session.find_property("twcc-stats") is not None:
                session.connect("notify::twcc-stats", _on_transport_feedback, weakref.ref(self))
            internal = self._rtpbin.emit("get-internal-session", 0)
            if internal is not None:
                internal.connect("on-feedback-rtcp", _on_feedback_rtcp, weakref.ref(self))
            self._rtpbin.get_static_pad("send_rtp_src_0").add_probe(
                Gst.PadProbeType.BUFFER, _sent_probe, weakref.ref(self)
            )
            rtx = pipeline.get_by_name("rtxsend")
            self._rtx_pad = rtx.get_static_pad("src") if rtx is not None else None
            self._rtx_probe = None
            self._drop_retransmissions(not self.retransmit)
            self._tail_copies = TailCopies(self.tail_copies_sent())
            self._tail_copies.attach(self._rtpbin, sink, partial(_copy_tails, weakref.ref(self)))
        else:
            link_all(pay, sink)
        if tap:
            self._add_tap(pipeline, tap[0])
        self._watch_keyframes(encoder, encoder_name)
        self.encoder_name = encoder_name
        self._encoder = encoder
        self._rate_filter = rate_filter
        self._scale_filter = scale_filter
        self._streaming_caps = StreamingThreadCaps()
        self._streaming_caps.watch(stamp.get_static_pad("sink"))  # upstream of both filters
        rate_filter.get_static_pad("src").add_probe(
            Gst.PadProbeType.BUFFER, _thinning_probe, weakref.ref(self)
        )
        return pipeline

    def _watch_keyframes(self, encoder: Any, encoder_name: str) -> None:
        """Force the clock's keyframes into the encoder; take a receiver's requests (the
        force-key-unit events rtpbin makes of PLI/FIR, or a depayloader's) through its limit."""
        Gst = gst()
        ref = weakref.ref(self)
        refresh = self.settings.uses_intra_refresh(encoder_name)
        with self._keyframes_lock:
            self.keyframes.restart()
            self.keyframes.interval_s = (
                REFRESH_KEYFRAME_INTERVAL_S if refresh else KEYFRAME_INTERVAL_S
            )
            self.keyframes.set_framerate(self.settings.framerate)
        if not refresh:
            self._keyframe_now = KeyframeNow(encoder.get_static_pad("sink"), self.name)
        encoder.get_static_pad("sink").add_probe(
            Gst.PadProbeType.BUFFER, _force_keyframe_probe, ref
        )
        encoder.get_static_pad("src").add_probe(
            Gst.PadProbeType.EVENT_UPSTREAM, _keyframe_request_probe, ref
        )
        encoder.get_static_pad("src").add_probe(Gst.PadProbeType.BUFFER, _encoded_probe, ref)

    def make_sink(self) -> Any:
        # AF41: a Wi-Fi (WMM) link queues video behind teleop's EF and telemetry, never ahead.
        sink = super().make_sink()
        sink.set_property("qos-dscp", VIDEO_DSCP)
        return sink

    def on_torn_down(self) -> None:
        super().on_torn_down()
        self._encoder = None
        self._rate_filter = None
        self._scale_filter = None
        self._streaming_caps = None
        with self._adapt_lock:
            self._rtpbin = None
        self._rtx_pad = None
        self._rtx_probe = None
        self._reports_seen.clear()
        self._transport_seen = None
        if self.wanted is StreamState.IDLE and self.feedback is not None:
            self.feedback.close()
            self.feedback = None
        if self._tail_copies is not None:
            self._tail_copies.close()
        if self._keyframe_now is not None:
            self._keyframe_now.close()
            self._keyframe_now = None

    def _add_tap(self, pipeline: Any, tee: Any) -> None:
        """tee → leaky queue → h264parse (SPS/PPS on every keyframe, Annex B, whole access
        units) → appsink: a slow consumer loses access units here, never the stream."""
        branch = [
            make(
                "queue",
                "tap_queue",
                leaky="downstream",
                max_size_buffers=TAP_QUEUE_BUFFERS,
                max_size_bytes=0,
                max_size_time=0,
            ),
            make("h264parse", "tap_parse", config_interval=-1),
            make(
                "capsfilter",
                "tap_caps",
                caps=caps("video/x-h264,stream-format=byte-stream,alignment=au"),
            ),
            make(
                "appsink",
                "tap",
                emit_signals=True,
                sync=False,
                async_=False,
                drop=True,
                max_buffers=TAP_QUEUE_BUFFERS,
            ),
        ]
        for element in branch:
            pipeline.add(element)
        link_all(tee, *branch)
        branch[-1].connect("new-sample", _on_access_unit, (weakref.ref(self), ntp_caps()))

    def _source_elements(self) -> list[Any]:
        s = self.settings
        size = f"width={s.width},height={s.height},framerate={s.camera_framerate}/1"
        if s.test_source:
            source = make("videotestsrc", "source", is_live=True, pattern=s.pattern)
            if s.motion:
                source.set_property("horizontal-speed", s.motion)
            return [source, make("capsfilter", caps=caps(f"video/x-raw,{size}"))]
        source = make("v4l2src", "source", device=s.device, do_timestamp=True)
        if s.source_format == "mjpeg":
            return [source, make("capsfilter", caps=caps(f"image/jpeg,{size}")), make("jpegdec")]
        if s.source_format == "raw":
            return [source, make("capsfilter", caps=caps(f"video/x-raw,{size}"))]
        raise MediaError(f"unknown camera format '{s.source_format}' (raw or mjpeg)")


def _on_access_unit(appsink: Any, data: tuple[weakref.ref[VideoOut], Any]) -> Any:
    """Streaming thread: hand one access unit (bytes, keyframe, capture time) to the sinks."""
    Gst = gst()
    ref, reference = data
    sample = appsink.emit("pull-sample")
    stream = ref()
    if sample is None or stream is None:
        return Gst.FlowReturn.OK
    buffer = sample.get_buffer()
    keyframe = not buffer.has_flags(Gst.BufferFlags.DELTA_UNIT)
    meta = buffer.get_reference_timestamp_meta(reference)
    if meta is not None and meta.timestamp:
        captured_ns = int(meta.timestamp) - NTP_UNIX_OFFSET_NS
    else:
        captured_ns = time.time_ns()
    payload = buffer.extract_dup(0, buffer.get_size())
    for sink in tuple(stream.access_unit_sinks):
        try:
            sink(payload, keyframe, captured_ns)
        except Exception:
            pass  # a consumer's failure never stops the stream; it counts its own errors
    return Gst.FlowReturn.OK


def _copy_tails(ref: weakref.ref[VideoOut]) -> bool:
    """Any thread: send each frame's last packet twice (few frames a second, far apart)?"""
    stream = ref()
    # The framerate asked for, not the one thinned for a full link: a copy would add to it.
    if stream is None:
        return False
    if stream.settings.framerate <= TAIL_COPY_MAX_FPS:
        return True
    # A lossy link's, but not into a queue that overflows (its loss is not the link's).
    return stream.lossy_link.on and stream.retransmit and not stream.keyframes.congested


def _thinning_probe(pad: Any, info: Any, ref: weakref.ref[VideoOut]) -> Any:
    """Streaming thread, before the encoder: drop frames while the stream is thinned (the
    encoder's rate control goes by timestamps: the bits go to the frames sent)."""
    stream = ref()
    if stream is None:
        return gst().PadProbeReturn.OK
    with stream._keyframes_lock:
        admitted = stream.budget.admit(time.monotonic())
        resuming = stream.keyframe_after_pause
    if not admitted:
        return gst().PadProbeReturn.DROP
    pay = stream.pipeline.get_by_name("pay") if resuming and stream.pipeline else None
    if pay is not None:
        # The picture restarts with this frame: what was sent before it is stale too (a frame
        # already in the encoder as the pause began went out after it, into the full queue,
        # and its retransmissions held the keyframe back ~100 ms, measured). The frames
        # before it are through the payloader: the encoder takes them one at a time, here.
        stream.stale_before = (int(pay.get_property("seqnum")) + 1) & 0xFFFF
    if stream.thinning <= 1:
        return gst().PadProbeReturn.OK
    if resuming:
        # The keyframe a drain pause ends with: the picture restarts with this frame, not
        # with the thinning's next one (measured: a frame, 33-66 ms, more frozen).
        stream._frames_seen = 0
        return gst().PadProbeReturn.OK
    stream._frames_seen += 1
    if stream._frames_seen % stream.thinning:
        return gst().PadProbeReturn.DROP
    return gst().PadProbeReturn.OK


def _retransmission_probe(pad: Any, info: Any, ref: weakref.ref[VideoOut]) -> Any:
    """Streaming thread, after the retransmitter: drop its packets while the stream says so
    (a link over its capacity drops them anyway, and they delay its recovery)."""
    stream = ref()
    if stream is None:
        return gst().PadProbeReturn.OK
    stale = stream.stale_until > time.monotonic()
    if stream.retransmit and not stale:
        return gst().PadProbeReturn.OK
    buffer = info.get_buffer()
    header = buffer.extract_dup(0, RTX_HEADER_READ) if buffer is not None else b""
    if len(header) < 2 or header[1] & 0x7F not in (RTX_PAYLOAD_TYPE, FEC_RTX_PAYLOAD_TYPE):
        return gst().PadProbeReturn.OK
    stale_packet = _sent_before(header, stream.stale_before)
    if stream.retransmit and not stale_packet:
        return gst().PadProbeReturn.OK
    if stale and stale_packet and header[1] & 0x7F == RTX_PAYLOAD_TYPE:
        emptied = emptied_retransmission(header, buffer.get_size())
        if emptied is None:
            return gst().PadProbeReturn.OK  # one emptied here, on its way out
        # Sent again without its media: the receivers stop waiting for it at once (their
        # jitter buffer held the keyframe after the pause behind it for its whole repair
        # budget, measured 100-200 ms) and take it for lost.
        stream.retransmissions_emptied += 1
        pad.push(gst().Buffer.new_wrapped(emptied))
        return gst().PadProbeReturn.DROP
    stream.retransmissions_dropped += 1
    return gst().PadProbeReturn.DROP


RTX_HEADER_READ = 64
"""Bytes of a retransmission read for its original sequence number (header, extensions)."""


def _payload_start(rtp_header: bytes) -> int:
    """Where an RTP packet's payload starts (after its CSRCs and header extensions)."""
    start = 12 + (rtp_header[0] & 0x0F) * 4
    if rtp_header[0] & 0x10 and len(rtp_header) >= start + 4:  # header extensions
        start += 4 + 4 * int.from_bytes(rtp_header[start + 2 : start + 4], "big")
    return start


GIVEN_UP_PAYLOAD = b"\x0c\x80"
"""The media a retransmission of a packet given up carries: an H.264 filler-data NAL unit
(type 12: no picture; x264 makes none here). A receiver takes it for that packet lost
(:func:`_given_up_probe`); rtph264depay crashes on an empty payload (GStreamer 1.22)."""


def emptied_retransmission(rtx_header: bytes, size: int) -> bytes | None:
    """A retransmission (``size`` bytes, its first bytes ``rtx_header``) with its media
    replaced by :data:`GIVEN_UP_PAYLOAD`, after its header and original sequence number
    (RFC 4588). None when it is that already, or its header was not read whole."""
    end = _payload_start(rtx_header) + 2
    if len(rtx_header) < end or size <= end + len(GIVEN_UP_PAYLOAD):
        return None
    # No padding: the cut took it (its length byte ended the packet).
    return bytes([rtx_header[0] & ~0x20 & 0xFF]) + rtx_header[1:end] + GIVEN_UP_PAYLOAD


def _sent_before(rtx_header: bytes, first_fresh: int) -> bool:
    """Whether a retransmission's original packet (its sequence number opens the payload,
    RFC 4588) came before ``first_fresh`` (16-bit sequence arithmetic)."""
    start = _payload_start(rtx_header)
    if len(rtx_header) < start + 2:
        return False  # not read here: counted as fresh
    original = int.from_bytes(rtx_header[start : start + 2], "big")
    return 0 < (first_fresh - original) & 0xFFFF < 0x8000


def _force_keyframe_probe(pad: Any, info: Any, ref: weakref.ref[VideoOut]) -> Any:
    """Streaming thread, before a raw frame enters the encoder: force it to a keyframe when
    the clock says so (the encoder applies a pending force-key-unit to its next frame). The
    encoder is found from the pad: a reference held by the probe would keep it alive. The event
    goes to the encoder's source pad, not to the element: ``Element.send_event`` takes the
    encoder's state lock, which a stop holds while it waits for this thread's stream lock (a
    deadlock, ~1 stop in 400 here, that left the pipeline abandoned and its memory held)."""
    stream = ref()
    encoder = pad.get_parent_element()
    if stream is not None and encoder is not None:
        now = time.monotonic()
        keyframe_now = stream._keyframe_now
        with stream._keyframes_lock:
            if keyframe_now is not None and keyframe_now.is_injecting():
                # The newest frame again, for a request: only while one still waits.
                wanted = stream.keyframes.answers_now(now)
                if not keyframe_now.admit(info.get_buffer(), wanted):
                    return gst().PadProbeReturn.DROP
            elif keyframe_now is not None:
                keyframe_now.keep(info.get_buffer())
            force = stream.keyframes.on_frame(now, stream.keyframe_after_pause)
            stream.keyframe_after_pause = False
        if force:
            event = _force_key_unit_event()
            stream._forced_seqnums.append(event.get_seqnum())
            encoder.get_static_pad("src").send_event(event)
    return gst().PadProbeReturn.OK


def _on_transport_feedback(session: Any, _spec: Any, ref: weakref.ref[VideoOut]) -> None:
    """RTCP's thread, at each transport feedback (every ~30 ms): adapt at once (the event
    loop's poll added up to 50 ms, more on a loaded machine: measured 0.18 s between polls)."""
    stream = ref()
    if stream is not None:
        stream.adapt_bitrate(time.monotonic())


QUEUE_OVERUSE_FRESH_S = 0.1
"""A queue seen packet by packet is acted on this soon or not at all (the lock was held)."""
TRANSPORT_SEQ_READ = 48
"""Bytes of each packet read for its transport-wide sequence number (header, extensions)."""


def _sent_probe(pad: Any, info: Any, ref: weakref.ref[VideoOut]) -> Any:
    """Streaming thread, each packet leaving rtpbin (media, retransmission, FEC): its
    transport-wide number, size and send time, for the per-packet feedback."""
    stream = ref()
    buffer = info.get_buffer()
    if stream is not None and buffer is not None:
        seq = transport_seq(buffer.extract_dup(0, TRANSPORT_SEQ_READ), TWCC_EXT_ID)
        if seq is not None:
            stream.send_history.on_sent(seq, buffer.get_size(), time.monotonic())
    return gst().PadProbeReturn.OK


def _on_feedback_rtcp(
    session: Any,
    kind: int,
    fmt: int,
    sender_ssrc: int,
    _media_ssrc: int,
    fci: Any,
    ref: weakref.ref[VideoOut],
) -> None:
    """RTCP's thread, each feedback message: a transport-wide one is read packet by packet;
    a queue it confirms adapts the bitrate at once."""
    stream = ref()
    if stream is None or kind != RTCP_RTPFB or fmt != TWCC_FMT or fci is None:
        return
    now = time.monotonic()
    payload = fci.extract_dup(0, fci.get_size())
    overuse = stream.queue_detector.on_feedback(payload, sender_ssrc, stream.send_history, now)
    stream.bitrate.note_queue(stream.queue_detector.queue_ms)
    if overuse is not None:
        stream._queue_overuse = overuse
        stream.adapt_bitrate(now)


def _encoded_probe(pad: Any, info: Any, ref: weakref.ref[VideoOut]) -> Any:
    """Streaming thread: one access unit out of the encoder; its size joins the sender's queue
    estimate."""
    stream = ref()
    if stream is None:
        return gst().PadProbeReturn.OK
    stream.frames_encoded += 1
    buffer = info.get_buffer()
    if buffer is not None:
        with stream._keyframes_lock:
            stream.budget.on_encoded(buffer.get_size(), time.monotonic())
    return gst().PadProbeReturn.OK


def _keyframe_request_probe(pad: Any, info: Any, ref: weakref.ref[VideoOut]) -> Any:
    """Any thread: a force-key-unit from downstream is a request, rate-limited by the clock."""
    Gst = gst()
    stream = ref()
    event = info.get_event()
    if stream is None or event is None or event.type != Gst.EventType.CUSTOM_UPSTREAM:
        return Gst.PadProbeReturn.OK
    structure = event.get_structure()
    if structure is None or structure.get_name() != "GstForceKeyUnit":
        return Gst.PadProbeReturn.OK
    if event.get_seqnum() in stream._forced_seqnums:
        return Gst.PadProbeReturn.OK  # our own, on its way to the encoder
    stream.request_keyframe()
    return Gst.PadProbeReturn.DROP  # the clock forces it on the next frame


def _force_key_unit_event() -> Any:
    Gst = gst()
    from gi.repository import GstVideo

    return GstVideo.video_event_new_upstream_force_key_unit(Gst.CLOCK_TIME_NONE, True, 0)


def _h264_caps(encoder_name: str) -> str:
    if encoder_name == "omxh264enc":
        # The OMX encoder only announces "baseline"; its output has no B-frames or FMO either.
        return "video/x-h264,profile=baseline"
    if encoder_name == "v4l2h264enc":
        # The Pi's encoder does not negotiate without a level.
        return "video/x-h264,profile=constrained-baseline,level=(string)4"
    return "video/x-h264,profile=constrained-baseline"


def _configure_encoder(encoder: Any, name: str, s: VideoSettings) -> None:
    """Low-latency, one slice per frame, keyframe every second, bitrate from settings."""
    kbps = s.effective_bitrate_kbps()
    if name == "x264enc":
        # threads=1: one slice per frame (Chromium mis-decodes multi-slice) and no frame
        # threading; zerolatency: no lookahead, no B-frames.
        set_prop(encoder, "tune", "zerolatency")
        set_prop(encoder, "speed-preset", "ultrafast")
        set_prop(encoder, "threads", 1)
        set_prop(encoder, "sliced-threads", False)
        set_prop(encoder, "bitrate", kbps)
        # A keyframe at most ~this much of the bitrate: x264's default (600 ms) let one
        # keyframe overflow a capacity-limited link's queue right after the bitrate fell.
        set_prop(encoder, "vbv-buf-capacity", X264_VBV_MS)
        if s.uses_intra_refresh(name):
            set_prop(encoder, "intra-refresh", True)
    elif name == "openh264enc":
        encoder.set_property("bitrate", kbps * 1000)
        _nick(encoder, "rate-control", "bitrate")
        _nick(encoder, "slice-mode", "n-slices")
        encoder.set_property("num-slices", 1)
        _nick(encoder, "complexity", "low")
        encoder.set_property("enable-frame-skip", False)
    elif name == "v4l2h264enc":
        encoder.set_property(
            "extra-controls",
            gst().Structure.from_string(
                f"controls,video_bitrate={kbps * 1000},repeat_sequence_header=1,h264_profile=1"
            )[0],
        )
    elif name == "omxh264enc":
        encoder.set_property("target-bitrate", kbps * 1000)
        _nick(encoder, "control-rate", "variable")
        if encoder.find_property("inline-header") is not None:
            encoder.set_property("inline-header", True)
    if s.uses_intra_refresh(name):
        # With intra refresh, x264's interval is the refresh wave's length: one a second.
        _set_keyframe_interval(encoder, name, s.framerate)
    else:
        _set_keyframe_interval(encoder, name, ENCODER_GOP_S * s.camera_framerate)


def _set_bitrate(encoder: Any, name: str, kbps: int) -> None:
    if name == "x264enc":
        encoder.set_property("bitrate", kbps)
    elif name == "openh264enc":
        encoder.set_property("bitrate", kbps * 1000)
    elif name == "omxh264enc":
        encoder.set_property("target-bitrate", kbps * 1000)
    elif name == "v4l2h264enc":
        controls = encoder.get_property("extra-controls")
        if controls is not None:
            controls = controls.copy()
            controls.set_value("video_bitrate", kbps * 1000)
            encoder.set_property("extra-controls", controls)


def _set_keyframe_interval(encoder: Any, name: str, frames: int) -> None:
    """The encoder's own interval (a backstop: the keyframe clock forces them sooner)."""
    if name == "x264enc":
        encoder.set_property("key-int-max", frames)
    elif name == "openh264enc":
        encoder.set_property("gop-size", frames)
    elif name == "omxh264enc" and encoder.find_property("periodicity-idr") is not None:
        encoder.set_property("periodicity-idr", frames)
    elif name == "v4l2h264enc":
        controls = encoder.get_property("extra-controls")
        if controls is not None:
            controls = controls.copy()
            controls.set_value("h264_i_frame_period", frames)
            encoder.set_property("extra-controls", controls)


def _nick(element: Any, key: str, value: str) -> None:
    set_prop(element, key, value)


class VideoIn(PipelineStream):
    """RTP/UDP H.264 → decoded frames, with a per-frame glass-to-glass latency figure."""

    kind = "video_in"

    def __init__(
        self,
        name: str,
        *,
        port: int,
        host: str = "0.0.0.0",
        sink: str = "fakesink",
        jitter_ms: int = 0,
        window: int = 2000,
        repair: bool = True,
        fec: bool = False,
        **kwargs: Any,
    ) -> None:
        super().__init__(name, **kwargs)
        self.repair = repair
        self.fec = fec
        """Rebuild lost packets from the sender's ULPFEC (``navcam.fec_max_percent``)."""
        """Ask the sender for lost packets and keyframes (its ``rtcp_port``: set_feedback)."""
        self.repairs: RepairReceiver | None = None
        self._feedback: tuple[str, int] = ("", 0)
        self.intra_refresh = False
        """The sender refreshes the picture by intra blocks (its ``intra_refresh``): after a
        loss, decode on (the damage heals within the refresh wave) instead of freezing to a
        keyframe asked for."""
        self.host = host
        self.port = port
        self.sink_factory = sink
        self.jitter_ms = jitter_ms
        self.frames = 0
        self.stamped = 0
        self.frames_depayloaded = 0
        self.given_up = 0
        self._depayloader_sink: Any = None
        self._watching_given_up = False
        """The probe for packets given up is on the depayloader only for a while after one
        arrived (:meth:`watch_given_up`): a Python probe on every packet there is a GIL
        round on the jitter buffer's thread each (a latency tail under load)."""
        self.given_up_watch_until = 0.0
        """Packets the sender said it gave up (:func:`_given_up_probe`): lost at once."""
        """Access units out of the depayloader, to the decoder (frames is what it decoded):
        where a frame went that every packet of reached the station."""
        self.rtp_bytes = 0
        """RTP bytes received (headers included, UDP/IP not), for the bitrate."""
        self.latencies: collections.deque[float] = collections.deque(maxlen=window)
        """Recent glass-to-glass latencies (ms), appended on the streaming thread."""
        self.last_latency_ms: float | None = None
        self.rtp_packets = 0
        self.rtp_lost = 0
        """RTP sequence numbers skipped (packets lost on the way, or late beyond reorder)."""
        self._last_seq: int | None = None
        self.last_frame_at: float | None = None
        self.longest_freeze_ms = 0.0
        self.longest_freeze_ended: float | None = None
        """time.monotonic() of the frame that ended the longest freeze (when it happened)."""
        """The longest wait between two decoded frames (a loss freezes to the next keyframe)."""
        self.gaps_ms: collections.deque[float] = collections.deque(maxlen=window)
        """Recent waits between two decoded frames (ms), appended on the streaming thread."""
        self.size: tuple[int, int] | None = None
        """The decoded picture's width and height (the sender may halve it on a slow link)."""

    def destination(self) -> str:
        return f"{self.host}:{self.port}"

    def watch_given_up(self, now: float) -> None:
        """Streaming thread (the socket's): a retransmission the sender gave up arrived; it
        comes out of the jitter buffer in order, where :func:`_given_up_probe` takes it for
        lost. Watched there for :data:`GIVEN_UP_WATCH_S` after the last one."""
        self.given_up_watch_until = now + GIVEN_UP_WATCH_S
        pad = self._depayloader_sink
        if not self._watching_given_up and pad is not None:
            self._watching_given_up = True
            pad.add_probe(gst().PadProbeType.BUFFER, _given_up_probe, weakref.ref(self))

    def describe(self) -> dict[str, Any]:
        return {
            **super().describe(),
            **self.latency_stats(),
            "rtp_packets": self.rtp_packets,
            "rtp_lost": self.rtp_lost,
            "longest_freeze_ms": round(self.longest_freeze_ms, 1),
            "longest_freeze_ended_monotonic": self.longest_freeze_ended,
            "frames_depayloaded": self.frames_depayloaded,
            "packets_given_up": self.given_up,
            # time.monotonic() of the newest frame (one clock for every process on the host:
            # the bench times the picture's return after a blackout by it).
            "last_frame_monotonic": self.last_frame_at,
            "size": list(self.size) if self.size is not None else None,
            **self.gap_stats(),
            **self.repair_stats(),
        }

    def set_feedback(self, host: str, port: int | None) -> None:
        """Where the sender takes RTCP feedback (its ``rtcp_port``); applied live. Loop."""
        self._feedback = (host, port or 0)
        if self.repairs is not None:
            self.repairs.set_feedback(host, port or 0)

    async def follow_sender(self, answer: dict[str, Any]) -> None:
        """Match the sender's ``intra_refresh`` and FEC (its ``start_stream`` answer): the
        pipeline is rebuilt when they differ (a depayloader already waiting for a keyframe
        keeps waiting whatever it is told, and the FEC decoder is placed at build). Loop."""
        refresh = answer.get("intra_refresh") is True
        fec_max = answer.get("fec_max_percent")
        fec = self.fec or (isinstance(fec_max, int) and fec_max > 0)
        if refresh == self.intra_refresh and fec == self.fec:
            return
        self.intra_refresh, self.fec = refresh, fec
        if self.pipeline is not None:
            await self.restart()

    def gap_stats(self) -> dict[str, Any]:
        """The waits between decoded frames of the recent window: percentiles, and the time
        frozen (the part of each gap over twice the usual one is a frozen picture)."""
        gaps = sorted(self.gaps_ms)
        if not gaps:
            return {}
        usual = statistics.median(gaps)

        def at(q: float) -> float:
            return round(gaps[min(len(gaps) - 1, int(len(gaps) * q))], 1)

        frozen = sum(gap - usual for gap in gaps if gap > 2 * usual)
        return {
            "gap_ms": {"p50": at(0.5), "p95": at(0.95), "p99": at(0.99), "max": at(1.0)},
            "frozen_pct": round(100 * frozen / max(1.0, sum(gaps)), 2),
        }

    def repair_stats(self) -> dict[str, Any]:
        if self.repairs is None:
            return {}
        return {"repair": vars(self.repairs.counters())}

    def count_packet(self, seq: int) -> None:
        """Streaming thread: one RTP packet; a gap in the sequence counts as lost."""
        self.rtp_packets += 1
        if self._last_seq is not None:
            gap = (seq - self._last_seq) & 0xFFFF
            if gap >= 0x8000:  # older than the last: late or duplicated, not a gap
                return
            self.rtp_lost += max(0, gap - 1)
        self._last_seq = seq

    def count_frame(self, now: float) -> None:
        """Streaming thread: one decoded frame."""
        if self.last_frame_at is not None:
            gap = (now - self.last_frame_at) * 1000
            if gap > self.longest_freeze_ms:
                self.longest_freeze_ms = gap
                self.longest_freeze_ended = now
            self.gaps_ms.append(gap)
        self.last_frame_at = now

    def recent_latency_ms(self, now: float | None = None) -> float | None:
        """The age of the picture: the median glass-to-glass latency of the last 30 frames
        plus the wait since the last one (a frozen picture is latency: the speed cap falls
        as the video fails), while playing, else None. ``now``: time.monotonic()."""
        if self.state is not StreamState.PLAYING or not self.latencies:
            return None
        median = float(statistics.median(list(self.latencies)[-30:]))
        if self.last_frame_at is None:
            return median
        waited = (time.monotonic() if now is None else now) - self.last_frame_at
        return median + max(0.0, waited) * 1000

    def latency_stats(self) -> dict[str, Any]:
        values = sorted(self.latencies)
        if not values:
            return {"frames": self.frames, "rtp_bytes": self.rtp_bytes, "latency_ms": None}
        return {
            "frames": self.frames,
            "rtp_bytes": self.rtp_bytes,
            "latency_ms": self.last_latency_ms,
            "latency_p50_ms": statistics.median(values),
            "latency_p95_ms": values[min(len(values) - 1, int(len(values) * 0.95))],
            "latency_p99_ms": values[min(len(values) - 1, int(len(values) * 0.99))],
        }

    def on_torn_down(self) -> None:
        if self.repairs is not None:
            self.repairs.close()

    def build(self) -> Any:
        Gst = gst()
        pipeline = Gst.Pipeline.new(f"{self.name}-in")
        source = make(
            "udpsrc", "source", address=self.host, port=self.port, caps=caps(RTP_VIDEO_CAPS)
        )
        chain = [source]
        if self.jitter_ms > 0 and not self.repair:
            chain.append(make("rtpjitterbuffer", latency=self.jitter_ms, drop_on_latency=True))
        decoder = make("avdec_h264", "decoder")
        if decoder.find_property("thread-type") is not None:
            # Frame threading would hold a frame back (+33 ms at 30 fps).
            _nick(decoder, "thread-type", "slice")
        sink = make(self.sink_factory, "sink")
        if sink.find_property("sync") is not None:
            sink.set_property("sync", False)
        depay = make("rtph264depay", "depay")
        if decoder.find_property("output-corrupt") is not None:
            decoder.set_property("output-corrupt", False)
        chain += [depay, decoder, make("videoconvert"), sink]
        for element in chain:
            pipeline.add(element)
        if self.repair:
            link_all(*chain[1:])
            self.repairs = add_repair_receiver(
                pipeline, source, depay, RTP_VIDEO_CAPS, fec=self.fec
            )
            self.repairs.set_feedback(*self._feedback)
        else:
            link_all(*chain)
        # After packet loss, freeze until the next keyframe instead of smearing (GOP ≤ 1 s).
        # With intra refresh there is no keyframe to wait for or ask for after a loss: the
        # damage heals within the refresh wave (and a new sweep starts on request).
        depay.set_property("wait-for-keyframe", not self.intra_refresh)
        if self.intra_refresh and depay.find_property("request-keyframe") is not None:
            depay.set_property("request-keyframe", False)
        if self.intra_refresh and self.repairs is not None:
            self.repairs.owed = None  # a request starts a new sweep: no keyframe answers it
        decoder.get_static_pad("src").add_probe(
            Gst.PadProbeType.BUFFER, _latency_probe, (weakref.ref(self), ntp_caps())
        )
        decoder.get_static_pad("src").add_probe(
            Gst.PadProbeType.EVENT_DOWNSTREAM, _size_probe, weakref.ref(self)
        )
        source.get_static_pad("src").add_probe(
            Gst.PadProbeType.BUFFER, _bytes_probe, weakref.ref(self)
        )
        depay.get_static_pad("src").add_probe(
            Gst.PadProbeType.BUFFER, _depayloaded_probe, weakref.ref(self)
        )
        self._depayloader_sink = depay.get_static_pad("sink")
        self._watching_given_up = False
        return pipeline


def _latency_probe(pad: Any, info: Any, data: tuple[weakref.ref[VideoIn], Any]) -> Any:
    """Streaming thread: count the frame and record its capture-to-decoded age."""
    ref, reference = data
    stream = ref()
    if stream is None:
        return gst().PadProbeReturn.OK
    stream.frames += 1
    stream.count_frame(time.monotonic())
    buffer = info.get_buffer()
    if buffer is not None:
        age = capture_age_ms(buffer, reference)
        if age is not None:
            stream.stamped += 1
            stream.last_latency_ms = age
            stream.latencies.append(age)
    return gst().PadProbeReturn.OK


def _given_up_probe(pad: Any, info: Any, ref: weakref.ref[VideoIn]) -> Any:
    """Streaming thread, out of the jitter buffer: a packet the sender gave up (sent before a
    drain pause, asked for after it: :data:`GIVEN_UP_PAYLOAD`) is lost, as the jitter buffer
    would have said at the end of its repair budget (the depayloader drops its frame and
    waits for the keyframe that follows); never a picture."""
    Gst = gst()
    stream = ref()
    buffer = info.get_buffer()
    if not _is_given_up(buffer):
        if stream is None or time.monotonic() > stream.given_up_watch_until:
            if stream is not None:
                stream._watching_given_up = False
            return Gst.PadProbeReturn.REMOVE  # passes this packet on, and stops looking
        return Gst.PadProbeReturn.OK
    packet = buffer.extract_dup(0, 4)
    if stream is not None:
        stream.given_up += 1
        if stream.repairs is not None:
            # The keyframe follows these packets (the sender gave them up for it): the
            # depayloader's own request for one, at this loss, is held (a second keyframe
            # 33 ms after the first, on the link just drained, traced).
            stream.repairs.asked_at = time.monotonic()
    seq = int.from_bytes(packet[2:4], "big")
    lost = Gst.Structure.new_from_string(
        f"GstRTPPacketLost, seqnum=(uint){seq}, timestamp=(guint64){buffer.pts},"
        " duration=(guint64)0, retry=(uint)0"
    )
    pad.send_event(Gst.Event.new_custom(Gst.EventType.CUSTOM_DOWNSTREAM, lost))
    return Gst.PadProbeReturn.DROP


GIVEN_UP_WATCH_S = 1.0
"""The depayloader is watched for packets given up this long after one arrived (the sender
gives up packets for a second after a drain pause)."""


def _is_given_up(buffer: Any) -> bool:
    """Whether an RTP packet (a retransmission, or what it restored) is one the sender gave
    up: its payload only :data:`GIVEN_UP_PAYLOAD` (after the original number, if RTX)."""
    size = buffer.get_size() if buffer is not None else 0
    if not 12 + len(GIVEN_UP_PAYLOAD) <= size <= RTX_HEADER_READ:
        return False
    packet = buffer.extract_dup(0, size)
    if packet[-len(GIVEN_UP_PAYLOAD) :] != GIVEN_UP_PAYLOAD or packet[0] & 0x20:
        return False
    media = size - len(GIVEN_UP_PAYLOAD)
    start = _payload_start(packet)
    return start == media or (packet[1] & 0x7F == RTX_PAYLOAD_TYPE and start + 2 == media)


def _depayloaded_probe(pad: Any, info: Any, ref: weakref.ref[VideoIn]) -> Any:
    """Streaming thread: one access unit to the decoder."""
    stream = ref()
    if stream is not None:
        stream.frames_depayloaded += 1
    return gst().PadProbeReturn.OK


def _size_probe(pad: Any, info: Any, ref: weakref.ref[VideoIn]) -> Any:
    """Streaming thread: the decoder's output caps give the picture's size."""
    Gst = gst()
    stream = ref()
    event = info.get_event()
    if stream is not None and event is not None and event.type == Gst.EventType.CAPS:
        structure = event.parse_caps().get_structure(0)
        ok_w, width = structure.get_int("width")
        ok_h, height = structure.get_int("height")
        if ok_w and ok_h:
            stream.size = (width, height)
    return Gst.PadProbeReturn.OK


def _bytes_probe(pad: Any, info: Any, ref: weakref.ref[VideoIn]) -> Any:
    """Streaming thread: count received RTP bytes."""
    stream = ref()
    buffer = info.get_buffer()
    if stream is not None and buffer is not None:
        stream.rtp_bytes += buffer.get_size()
        header = buffer.extract_dup(0, 4)
        # The media and its FEC share one sequence; retransmissions have their own.
        if len(header) == 4 and header[1] & 0x7F in (PAYLOAD_TYPE, FEC_PAYLOAD_TYPE):
            stream.count_packet(int.from_bytes(header[2:4], "big"))
        elif len(header) == 4 and header[1] & 0x7F == RTX_PAYLOAD_TYPE and _is_given_up(buffer):
            stream.watch_given_up(time.monotonic())
    return gst().PadProbeReturn.OK
