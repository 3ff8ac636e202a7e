"""Repair on a video path: RTCP feedback, NACK + retransmission (RFC 4588), keyframes on request.

Sender (:func:`add_repair_sender`): payloader → ``rtpbin`` (AVPF profile) with an
``rtprtxsend`` keeping the last :data:`RTX_HISTORY_MS` of packets → the stream's
``multiudpsink``; the receivers' RTCP (receiver reports, NACK, PLI/FIR) arrives on a UDP port
of its own (:class:`FeedbackSocket`, announced as ``rtcp_port``). A NACK is answered by the
packet again (payload type :data:`RTX_PAYLOAD_TYPE`, its own SSRC, same UDP port); a PLI/FIR
becomes a force-key-unit event that :class:`~brasidas.media.video.VideoOut` rate-limits.

Receiver (:func:`add_repair_receiver`): ``udpsrc`` → ``rtpbin`` with ``rtprtxreceive`` and a
jitter buffer that asks for a missing packet at once and waits for it at most
:data:`REPAIR_LATENCY_MS` (contiguous packets pass straight through: the buffer delays only a
frame that has a hole, and never beyond its budget) → the depayloader, which asks for a
keyframe (PLI) when a packet stays lost; the feedback goes to the platform's ``rtcp_port``
(:meth:`RepairReceiver.set_feedback`, from the ``start_stream`` answer). A receiver without
feedback (no ``rtcp_port``, an old platform) still works: it only cannot ask.
"""

from __future__ import annotations

import os
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from brasidas.media.gst import caps, gst, make
from brasidas.media.nack import GapWatch, generic_nack
from brasidas.media.reask import (
    RTX_HEADER_READ,
    ReaskFollower,
    attach_early_reask,
    rtx_original_seq,
)

MEDIA_PAYLOAD_TYPE = 96
"""The H.264 packets' payload type (the sender's ``rtph264pay pt``)."""
RTX_PAYLOAD_TYPE = 97
"""RFC 4588 retransmissions of payload type 96, sent on the stream's own port."""
RTX_HISTORY_MS = 1000
"""How far back the sender can retransmit (beyond the receiver's wait, for a slow NACK)."""
REPAIR_LATENCY_MS = 200
"""The longest a frame with a hole waits for its repair: well inside the deadman's 500 ms,
long enough for two or three tries on a 50 ms round trip. Then it is dropped, and the
depayloader asks for a keyframe."""
RTX_DELAY_MS = 0
"""Ask for a missing packet as soon as the gap shows."""
RTX_MAX_RETRIES = 5
"""Asks per missing packet (at 10 % loss each way a try fails 19 % of the time: 5 tries leave
0.03 % unrepaired). Unlimited (the default), a packet is asked for every few ms for
the whole budget: measured at 10 % loss, ~4 retransmissions per lost packet, and behind a
capacity limit the retransmissions filled the link (congestion collapse)."""
RTX_RETRY_FIRST_MS = 40
"""The wait before asking again for a packet still missing, until a round trip is measured."""
RTX_RETRY_MIN_MS = REPAIR_LATENCY_MS // (RTX_MAX_RETRIES + 1)
"""The tries spread over the budget: packed closer (15 ms measured), a loaded machine's
stall of 50-100 ms used them all up at once, and 30 fps at 10 % loss lost packets for good.
A 10 ms floor (19 tries) was tried with the NACK sent at once: g2g p95 at 10 % loss 18 ms
against 57 on a quiet machine, but at load 8-12 the retries outran the stalled round trip
(2.4 retransmissions per lost packet, 84 % of the frames shown against 99 %)."""
RTX_RETRY_EVERY_S = 0.5
"""How often the wait is set again from the measured round trip."""
FEEDBACK_INTERVAL_NS = 20_000_000
"""Regular receiver reports no closer than 20 ms: what the link really carries (~4 kB/s)."""
FEEDBACK_BYTES_PER_S = 1_000_000.0
"""The RTCP budget the receiver's session plans with: what it may send, not what it sends
(the regular reports stay :data:`FEEDBACK_INTERVAL_NS` apart; the rest is feedback, which
only a loss asks for). AVPF sends feedback early only once per regular interval T_rr, which
this budget sets: at 64 kB/s T_rr was ~15-40 ms, and as the transport-wide feedback (every
25 ms) takes those early slots too, a NACK left the receiver 13 ms after its gap showed
(median; p90 23 ms), for a repair the link returns in 1 ms. At this budget T_rr is under a
millisecond: the NACK leaves at once (median 1.5 ms, p90 3 ms), at ~50 kbit/s of feedback at
10 % loss (36 before; reduced-size packets, :data:`REDUCED_SIZE_FEEDBACK`)."""
REDUCED_SIZE_FEEDBACK = True
"""Early feedback as the NACK or PLI alone (RFC 5506), not a whole report with it: the
feedback sent at once costs a third fewer bytes. The sender's rtpsession accepts it."""
TRANSPORT_FEEDBACK_INTERVAL_NS = 25_000_000
"""Transport-wide feedback (each packet's arrival) at most this far apart, not at each
frame's last packet: a queue over the link's capacity delays and drops those last packets,
and the sender heard nothing for 140 ms after a capacity drop (measured)."""
FEC_PAYLOAD_TYPE = 100
"""ULPFEC (RFC 5109) packets, in the media stream's own sequence (same SSRC and port)."""
FEC_RTX_PAYLOAD_TYPE = 101
"""Retransmissions of FEC packets: one lost and never repaired reads as a lost frame."""
_RTX_PT_MAP = (
    f"application/x-rtp-pt-map,96=(uint){RTX_PAYLOAD_TYPE},"
    f"{FEC_PAYLOAD_TYPE}=(uint){FEC_RTX_PAYLOAD_TYPE}"
)
FEC_STORAGE_MS = REPAIR_LATENCY_MS + 100
"""How long the receiver keeps packets to rebuild a lost one from (past the repair wait)."""
FEC_CAPS = "application/x-rtp,media=video,clock-rate=90000,encoding-name=ULPFEC"
FEEDBACK_CAPS = (
    "rtcp-fb-nack=(boolean)true,rtcp-fb-nack-pli=(boolean)true,rtcp-fb-ccm-fir=(boolean)true"
)


class FeedbackSocket:
    """The platform's RTCP port for one stream: bound at once (the port is announced before
    the pipeline plays), handed to ``udpsrc``; kept across pipeline rebuilds."""

    def __init__(self, host: str = "0.0.0.0", port: int = 0) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host, port))
        self.port: int = self.sock.getsockname()[1]

    def gio_socket(self) -> Any:
        """A GSocket of its own for one pipeline (it closes its copy of the descriptor)."""
        from gi.repository import Gio

        return Gio.Socket.new_from_fd(os.dup(self.sock.fileno()))

    def close(self) -> None:
        self.sock.close()


def add_repair_sender(
    pipeline: Any, payloader: Any, rtp_sink: Any, feedback: FeedbackSocket
) -> Any:
    """Link ``payloader`` → rtpbin (with retransmission) → ``rtp_sink``; RTCP in from
    ``feedback``. Returns the rtpbin. The elements must already be in ``pipeline``."""
    rtpbin = make("rtpbin", "rtpbin", rtp_profile="avpf")
    rtpbin.connect("request-aux-sender", _aux_sender)
    rtpbin.connect("request-fec-encoder", _fec_encoder)
    # The reports go nowhere: the receivers need none to ask (NACK, PLI), and sending them
    # would need a second port at each station.
    reports = make("fakesink", "rtcp_reports", sync=False, async_=False)
    rtcp_in = make("udpsrc", "rtcp_in", caps=caps("application/x-rtcp"))
    rtcp_in.set_property("socket", feedback.gio_socket())
    for element in (rtpbin, reports, rtcp_in):
        pipeline.add(element)
    _link(payloader, "src", rtpbin, "send_rtp_sink_0")
    _link(rtpbin, "send_rtp_src_0", rtp_sink, "sink")
    _link(rtpbin, "send_rtcp_src_0", reports, "sink")
    _link(rtcp_in, "src", rtpbin, "recv_rtcp_sink_0")
    return rtpbin


TAIL_COPY_MAX_FPS = 10
"""At this framerate or below each frame's last packet is sent twice (:class:`TailCopies`)."""


LOSSY_ASKED_ON = 0.03
"""A link is lossy (:class:`LossyLink`) while at least this share of the packets is asked for
again (NACK). At 10 % loss a tenth of the 30 fps frames lost their last packet, which showed
only with the next frame, 33 ms on (g2g p95 ~60 ms): above :data:`TAIL_COPY_MAX_FPS` the
sender copies the last packets only on a lossy link; and the receiver asks for each missing
packet twice there (:meth:`RepairReceiver.on_media_packet`)."""
LOSSY_ASKED_OFF = 0.01
"""... and until the share fell below this (no flapping around one threshold)."""
LOSSY_WINDOW_S = 1.0


@dataclass
class LossyLink:
    """Sans-IO: whether a link is lossy, from the share of the packets sent that were asked
    for again (NACK) in the last :data:`LOSSY_WINDOW_S`: at the sender, the requests it got;
    at a receiver, the packets it asked for. Not from the receivers' reported loss: RTCP counts
    a copy as a packet received, so the loss would read ~0 once the copies are on (and feed the
    bitrate controller that too)."""

    on: bool = False
    mark: tuple[float, int, int] | None = None
    """(time, retransmission requests, newest sequence number) at the window's start."""

    def update(self, requests: int, seq: int, now: float) -> bool:
        """The NACK count and newest sequence number at ``now`` (s): is the link lossy?"""
        if self.mark is None or requests < self.mark[1]:
            self.mark = (now, requests, seq)
            return self.on
        at, asked_before, seq_before = self.mark
        if now - at < LOSSY_WINDOW_S:
            return self.on
        self.mark = (now, requests, seq)
        sent = (seq - seq_before) & 0xFFFF
        if sent > 0:
            share = (requests - asked_before) / sent
            self.on = share >= (LOSSY_ASKED_OFF if self.on else LOSSY_ASKED_ON)
        return self.on


class SinkSocket:
    """Datagrams of our own sent from a ``multiudpsink``'s socket to each of its clients. From
    another port a peer's RTP session takes them for another source colliding with the
    stream's SSRC and drops them. Used from one streaming thread at a time."""

    def __init__(self, sink: Any) -> None:
        self.sink = sink
        self.sock: socket.socket | None = None
        self.closed = False

    def send(self, packet: bytes) -> int:
        """``packet`` to each client now: how many it went to (none before the sink has its
        socket, or where the buffer is full or the peer unreachable: it is dropped, as a
        datagram on a link would be)."""
        if self.sock is None:
            if self.closed:
                return 0
            from gi.repository import Gio  # noqa: F401 (the GSocket's methods need its typelib)

            used = self.sink.get_property("used-socket")
            if used is None:
                return 0
            self.sock = socket.socket(fileno=os.dup(used.get_fd()))  # non-blocking (GLib's)
        sent = 0
        for client in str(self.sink.get_property("clients") or "").split(","):
            host, _, port = client.rpartition(":")
            if host and port.isdigit():
                try:
                    self.sock.sendto(packet, (host, int(port)))
                    sent += 1
                except OSError:
                    pass
        return sent

    def close(self) -> None:
        self.closed = True
        if self.sock is not None:
            self.sock.close()
            self.sock = None


class TailCopies:
    """Each frame's last packet (RTP marker) sent a second time, as is, while the framerate is
    at most :data:`TAIL_COPY_MAX_FPS`. A receiver sees a packet missing only when a later one
    arrives: a frame's last packet lost at 5 fps showed only with the next frame, 200 ms on,
    and the frame came a frame late (gap p95 400 ms at 10 % loss). The copy costs a packet a
    frame (about a tenth of a 5 fps stream); a receiver's jitter buffer drops it as a
    duplicate when the first arrived. (As a retransmission it would not do: a jitter buffer
    drops a retransmission it did not ask for.) Sent through the stream's own UDP socket:
    from another port, the receiver's RTP session takes it for an SSRC collision and drops it.
    One per pipeline (its sink's socket); ``sent`` carries over."""

    def __init__(self, sent: int = 0) -> None:
        self.out: SinkSocket | None = None
        self.sent = sent
        self._probe: tuple[Any, int] | None = None
        self._follow: Callable[[], None] = lambda: None
        self._lock = threading.Lock()  # followed from the event loop and RTCP's thread

    def attach(self, rtpbin: Any, sink: Any, wanted: Callable[[], bool]) -> None:
        """Copy the marker packets leaving ``rtpbin`` to ``sink``'s clients while ``wanted()``
        (the stream's framerate is at most :data:`TAIL_COPY_MAX_FPS`); call :meth:`follow`
        when that may have changed."""
        pad = rtpbin.get_static_pad("send_rtp_src_0")

        def follow() -> None:
            # The probe is on the pad only while copies are wanted: at 30 fps every packet
            # would otherwise take the GIL on the streaming thread for nothing.
            if wanted() and self._probe is None:
                probe = pad.add_probe(gst().PadProbeType.BUFFER, _copy_tail, (self, sink, wanted))
                self._probe = (pad, probe)
            elif not wanted() and self._probe is not None:
                self._probe[0].remove_probe(self._probe[1])
                self._probe = None

        self._follow = follow
        follow()

    def follow(self) -> None:
        """Any thread: add or remove the copying as the stream's framerate (or the link's
        loss) now asks."""
        with self._lock:
            self._follow()

    def send(self, packet: bytes, sink: Any) -> None:
        """Streaming thread: ``packet`` to each of ``sink``'s clients, from its socket."""
        if self.out is None:
            self.out = SinkSocket(sink)
        self.sent += self.out.send(packet)

    def close(self) -> None:
        self._probe = None
        self._follow = lambda: None
        if self.out is not None:
            self.out.close()
            self.out = None


def _copy_tail(pad: Any, info: Any, data: tuple[TailCopies, Any, Callable[[], bool]]) -> Any:
    """Streaming thread: a marker packet of the media (not a retransmission) is sent again."""
    copies, sink, wanted = data
    buffer = info.get_buffer()
    if buffer is None or not wanted():
        return gst().PadProbeReturn.OK
    header = buffer.extract_dup(0, 2)
    if len(header) == 2 and header[1] == 0x80 | MEDIA_PAYLOAD_TYPE:
        copies.send(buffer.extract_dup(0, buffer.get_size()), sink)
    return gst().PadProbeReturn.OK


def _fec_encoder(rtpbin: Any, session: int) -> Any:
    # Off (0 %) until the receivers report loss: the share follows the link (VideoOut).
    return make("rtpulpfecenc", "fecenc", pt=FEC_PAYLOAD_TYPE, percentage=0, multipacket=True)


def fec_percentage(loss: float, most: int) -> int:
    """The FEC overhead for a link losing ``loss`` (0-1): none on a clean link, then about
    three times the loss (one XOR packet rebuilds one loss in its group, so the groups must
    be short enough to hold at most one loss most of the time), at most ``most``."""
    if loss < 0.01 or most <= 0:
        return 0
    return min(most, max(5, round(300 * loss / 5) * 5))


def _aux_sender(rtpbin: Any, session: int) -> Any:
    Gst = gst()
    bin_ = Gst.Bin.new(f"rtx_send_{session}")
    rtx = make(
        "rtprtxsend",
        "rtxsend",
        payload_type_map=Gst.Structure.new_from_string(_RTX_PT_MAP),
        max_size_time=RTX_HISTORY_MS,
        max_size_packets=0,
    )
    bin_.add(rtx)
    bin_.add_pad(Gst.GhostPad.new(f"src_{session}", rtx.get_static_pad("src")))
    bin_.add_pad(Gst.GhostPad.new(f"sink_{session}", rtx.get_static_pad("sink")))
    return bin_


@dataclass
class RepairCounters:
    """The receiver's view of the link, from its jitter buffer (read on the event loop)."""

    lost: int = 0
    """Packets given up on (not repaired within the budget)."""
    late: int = 0
    retransmission_requests: int = 0
    repaired: int = 0
    """Packets that arrived by retransmission in time."""
    rtt_ms: float | None = None
    keyframe_requests: int = 0
    """Losses the depayloader answered by asking the sender for a keyframe."""
    fec_recovered: int = 0
    """Packets rebuilt from the ULPFEC packets, without a retransmission."""
    keyframes_after_silence: int = 0
    """Keyframes asked at the first packet after a silence that skipped frames past their
    deadline (:class:`SilenceWatch`), not after the repairs that could no longer help."""
    keyframe_requests_held: int = 0
    """The depayloader's own requests dropped because one was asked just before."""
    early_reasks: int = 0
    """Packets asked for once more a round trip after their first ask, before the jitter
    buffer's own retry (:mod:`brasidas.media.reask`)."""
    keyframes_asked_again: int = 0
    """Keyframe requests sent again because no keyframe came :data:`KEYFRAME_ANSWER_S` after
    the last (the request or the keyframe lost on the link: :class:`KeyframeOwed`)."""
    keyframe_owed: bool = False
    """A keyframe was asked for and none has come out of the depayloader since."""
    asked_at_once: int = 0
    """Packets asked for (NACK) the moment their gap arrived, by the receiver's own probe
    (:meth:`RepairReceiver.on_media_packet`), not on RTCP's schedule."""
    asks_copied: int = 0
    """Of those, packets the jitter buffer asked for again as its own first ask: a copy of
    the NACK, sent only while the link is lossy (:class:`LossyLink`)."""


SILENCE_DROPOUT_MS = 1
"""The jitter buffer's ``max-dropout-time`` while a silence beyond repair ends: any gap of
at least its floor (30 packets) is then given up at once, not asked for again."""
SILENCE_FASTSTART_PACKETS = 3
"""... and its ``faststart-min-packets`` meanwhile: the packets after that gap go out as soon
as this many are in a row, not after the whole ``latency`` (a new stream's wait)."""
DEFAULT_DROPOUT_MS = 60000
"""rtpjitterbuffer's own ``max-dropout-time`` (and ``faststart-min-packets`` 0), set back."""

KEYFRAME_ASKED_HOLD_S = 0.15
"""After the receiver asked for a keyframe at a silence's end, the depayloader's own request
(made once the jitter buffer has given the silence's packets up, ~5-40 ms later) would only
make the sender defer a second keyframe by its rate limit: dropped for this long."""
KEYFRAME_ANSWER_S = 0.3
"""How long a keyframe asked for may take to come out of the depayloader before it is asked
again: the request's way to the sender, the keyframe's way back (the sender answers at once)
and the jitter buffer's wait for its repairs (:data:`REPAIR_LATENCY_MS`)."""
KEYFRAME_ASKS_AGAIN_MAX = 3
"""Asked again at most this often for one keyframe owed: a sender that cannot answer (or a
link that carries nothing back) is not asked every :data:`KEYFRAME_ANSWER_S` for ever; the
periodic keyframe heals the picture then."""


@dataclass
class KeyframeOwed:
    """Sans-IO: a keyframe asked for (PLI/FIR) that has not come yet, and when to ask again.
    A request is one RTCP packet: lost on the link (1 in 20 at 5 % loss), nothing else asked
    (the depayloader asks once per loss, and its request right after a silence's is held), and
    the picture stayed broken until the encoder's next periodic keyframe. Times in seconds."""

    due: float | None = None
    """When the keyframe is overdue (None: none owed)."""
    asks_left: int = 0
    asked_again: int = 0

    def asked(self, now: float) -> None:
        """A request went to the sender (the receiver's own or the depayloader's)."""
        if self.due is None:
            self.asks_left = KEYFRAME_ASKS_AGAIN_MAX
        self.due = now + KEYFRAME_ANSWER_S

    def arrived(self) -> None:
        """A keyframe came out of the depayloader: the picture restarts, nothing is owed."""
        self.due = None

    def ask_again(self, now: float) -> bool:
        """At each packet: True when the keyframe is overdue and may be asked for again (it
        then counts as asked now)."""
        if self.due is None or now < self.due:
            return False
        if self.asks_left <= 0:
            self.due = None  # given up: the periodic keyframe comes within a second
            return False
        self.asks_left -= 1
        self.asked_again += 1
        self.due = now + KEYFRAME_ANSWER_S
        return True


@dataclass
class SilenceWatch:
    """Sans-IO: each media packet's arrival (sequence number, RTP timestamp, time) against the
    one before. When the link was silent so long that a whole frame was skipped and that
    frame's display deadline (due at the silence's start + a frame, plus the jitter buffer's
    :data:`REPAIR_LATENCY_MS`) has passed, its repair comes too late: the picture can only
    come back with a keyframe, and :meth:`on_packet` says so at once, at the first packet after
    the silence. A shorter silence (a 100 ms blackout at 30 fps) is repaired in time; so is a
    lost packet at 5 fps (its frame is 200 ms away, not skipped)."""

    latency_s: float = REPAIR_LATENCY_MS / 1000
    clock_rate: int = 90000
    last: tuple[int, int, float] | None = None
    """(sequence number, RTP timestamp, arrival) of the newest packet."""
    frame_ticks: int = 0
    """RTP ticks between two consecutive frames (learnt where no packet was missing)."""

    def on_packet(self, seq: int, timestamp: int, now: float) -> bool:
        """One media packet arrived at ``now`` (seconds): True if a keyframe is needed now."""
        if self.last is None:
            self.last = (seq, timestamp, now)
            return False
        last_seq, last_timestamp, last_arrival = self.last
        seq_step = (seq - last_seq) & 0xFFFF
        ticks = (timestamp - last_timestamp) & 0xFFFFFFFF
        if seq_step == 0 or seq_step >= 0x8000 or ticks >= 0x80000000:
            return False  # a duplicate or a reordered packet: the newest stays the newest
        self.last = (seq, timestamp, now)
        if seq_step == 1:
            if ticks > 0:
                self.frame_ticks = ticks
            return False
        if self.frame_ticks <= 0 or 2 * ticks < 3 * self.frame_ticks:
            return False  # no whole frame skipped: the missing packets are repaired in time
        first_skipped_due = last_arrival + self.frame_ticks / self.clock_rate
        return now >= first_skipped_due + self.latency_s


@dataclass
class RepairReceiver:
    """The receive side's rtpbin, its feedback sink, and its counters."""

    rtpbin: Any
    feedback_sink: Any
    jitterbuffers: list[Any] = field(default_factory=list)
    reasks: list[ReaskFollower] = field(default_factory=list)
    fec_decoders: list[Any] = field(default_factory=list)
    keyframe_requests: int = 0
    silence: SilenceWatch = field(default_factory=SilenceWatch)
    keyframes_after_silence: int = 0
    keyframe_requests_held: int = 0
    asked_at: float | None = None
    """time.monotonic() of the newest keyframe asked after a silence."""
    skipping_until: float | None = None
    """The jitter buffers give a silence's gap up at once until then (:meth:`skip_silence`)."""
    owed: KeyframeOwed | None = field(default_factory=KeyframeOwed)
    """The keyframe asked for and not come yet (None: not followed, as with intra refresh,
    where no keyframe answers a request)."""
    depayloader_sink: Any = None
    session: Any = None
    """The RTP session (its ``internal-ssrc`` signs the NACKs sent at once)."""
    gaps: GapWatch = field(default_factory=GapWatch)
    lossy: LossyLink = field(default_factory=LossyLink)
    asked_at_once: int = 0
    feedback_out: SinkSocket | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _owed_lock: threading.Lock = field(default_factory=threading.Lock)
    """The keyframe owed: asked on the streaming threads, paid on the jitter buffer's."""

    def set_feedback(self, host: str, port: int) -> None:
        """Send RTCP feedback to the sender's ``rtcp_port`` (applied live)."""
        self.feedback_sink.set_property("clients", f"{host}:{port}" if port else "")

    def close(self) -> None:
        """The pipeline is torn down: the socket the NACKs sent at once went from is closed."""
        if self.feedback_out is not None:
            self.feedback_out.close()

    def on_media_packet(self, ssrc: int, seq: int, now: float, *, silence: bool) -> None:
        """Streaming thread, each packet of the media's sequence as it comes off the socket
        (before the jitter buffer): the packets missing just before it are asked for (NACK)
        now, not on RTCP's schedule (:mod:`brasidas.media.nack`), unless the gap is a silence
        beyond repair. The jitter buffer's own first ask for them (~1.5 ms later) is then a
        copy: dropped, except on a lossy link, where a lost NACK cost its frame a second try
        a round trip later (at 10 % loss each way a first try failed 19 % of the time, and
        those frames were glass-to-glass p95). The sender answers each copy it gets."""
        missing = self.gaps.on_packet(ssrc, seq)
        out = self.feedback_out
        if missing and not silence and out is not None and self.session is not None:
            own = int(self.session.get_property("internal-ssrc"))
            if out.send(generic_nack(own, ssrc, missing)):
                self.asked_at_once += len(missing)
                for follower in self.reasks:
                    follower.asked_at_once(missing, now)
        lossy = self.lossy.update(self.asked_at_once, seq, now)
        for follower in self.reasks:
            follower.copies = lossy

    def counters(self) -> RepairCounters:
        counters = RepairCounters(
            keyframe_requests=self.keyframe_requests,
            keyframes_after_silence=self.keyframes_after_silence,
            keyframe_requests_held=self.keyframe_requests_held,
        )
        owed = self.owed
        if owed is not None:
            with self._owed_lock:
                counters.keyframes_asked_again = owed.asked_again
                counters.keyframe_owed = owed.due is not None
        with self._lock:
            buffers = list(self.jitterbuffers)
            decoders = list(self.fec_decoders)
            counters.early_reasks = sum(follower.reask.reasked for follower in self.reasks)
            counters.asks_copied = sum(follower.copied for follower in self.reasks)
        counters.asked_at_once = self.asked_at_once
        for decoder in decoders:
            counters.fec_recovered += int(decoder.get_property("recovered"))
        for jitterbuffer in buffers:
            stats = jitterbuffer.get_property("stats")
            counters.lost += _uint(stats, "num-lost")
            counters.late += _uint(stats, "num-late")
            counters.retransmission_requests += _uint(stats, "rtx-count")
            counters.repaired += _uint(stats, "rtx-success-count")
            ok, rtt = stats.get_uint64("rtx-rtt")
            if ok and rtt:
                counters.rtt_ms = round(rtt / 1e6, 1)
        return counters

    def ask_keyframe(self, now: float) -> None:
        """Streaming thread: a PLI to the sender now, the way the depayloader asks (upstream
        from its sink pad: the RTP session turns it into the feedback packet at once)."""
        pad = self.depayloader_sink
        if pad is None or not pad.is_linked():
            return
        self.asked_at = now
        self.keyframes_after_silence += 1
        _push_keyframe_request(pad, _SILENCE_KEYFRAME_REQUEST)

    def keyframe_asked(self, now: float) -> None:
        """Any thread: a keyframe request went to the sender."""
        owed = self.owed
        if owed is not None:
            with self._owed_lock:
                owed.asked(now)

    def keyframe_arrived(self) -> None:
        """Streaming thread: a keyframe came out of the depayloader."""
        owed = self.owed
        if owed is not None and owed.due is not None:
            with self._owed_lock:
                owed.arrived()

    def ask_again_if_owed(self, now: float) -> None:
        """Streaming thread, at each media packet: the keyframe asked for is asked for again
        when it has not come in :data:`KEYFRAME_ANSWER_S` (:class:`KeyframeOwed`)."""
        owed = self.owed
        pad = self.depayloader_sink
        if owed is None or owed.due is None or pad is None or not pad.is_linked():
            return
        with self._owed_lock:
            again = owed.ask_again(now)
        if again:
            self.asked_at = now  # the depayloader's own request meanwhile is held, as above
            _push_keyframe_request(pad, _KEYFRAME_ASKED_AGAIN)

    def skip_silence(self, now: float) -> None:
        """Streaming thread, before the packet that ended the silence enters the jitter buffer:
        its frames are beyond repair and the picture comes back only with the keyframe just
        asked, so the gap is not asked for again and does not hold that keyframe back. (With
        their defaults the jitter buffers asked for the last ``latency`` of the silence's
        packets, ~60 at 30 fps, and let nothing out until those had come: the keyframe waited
        5-35 ms behind retransmissions that no decoder could use.) A gap of at least 30 packets
        makes rtpjitterbuffer start afresh at the first packets in a row after it."""
        with self._lock:
            buffers = list(self.jitterbuffers)
        for jitterbuffer in buffers:
            jitterbuffer.set_property("max-dropout-time", SILENCE_DROPOUT_MS)
            jitterbuffer.set_property("faststart-min-packets", SILENCE_FASTSTART_PACKETS)
        self.skipping_until = now + KEYFRAME_ASKED_HOLD_S

    def end_skipping(self, now: float) -> None:
        """Streaming thread: the jitter buffers' own settings back once the silence's gap was
        given up (a later gap is asked for again as usual)."""
        if self.skipping_until is None or now < self.skipping_until:
            return
        self.skipping_until = None
        with self._lock:
            buffers = list(self.jitterbuffers)
        for jitterbuffer in buffers:
            jitterbuffer.set_property("max-dropout-time", DEFAULT_DROPOUT_MS)
            jitterbuffer.set_property("faststart-min-packets", 0)


_SILENCE_KEYFRAME_REQUEST = (
    "GstForceKeyUnit, running-time=(guint64)18446744073709551615, all-headers=(boolean)true,"
    " count=(uint)0, after-silence=(boolean)true"
)
"""The depayloader's own request's fields (the RTP session reads them), and a mark of ours."""
_KEYFRAME_ASKED_AGAIN = (
    "GstForceKeyUnit, running-time=(guint64)18446744073709551615, all-headers=(boolean)true,"
    " count=(uint)0, asked-again=(boolean)true"
)
"""The same, asked again for a keyframe owed (never held, and not a new debt)."""


def _push_keyframe_request(pad: Any, fields: str) -> None:
    """Streaming thread: a keyframe request upstream from the depayloader's sink pad (the RTP
    session turns it into a PLI/FIR at once)."""
    Gst = gst()
    pad.push_event(
        Gst.Event.new_custom(Gst.EventType.CUSTOM_UPSTREAM, Gst.Structure.new_from_string(fields))
    )


def _uint(structure: Any, key: str) -> int:
    ok, value = structure.get_uint64(key)
    return int(value) if ok else 0


def add_repair_receiver(
    pipeline: Any, source: Any, depayloader: Any, rtp_caps: str, *, fec: bool = False
) -> RepairReceiver:
    """Link ``source`` (udpsrc) → rtpbin → ``depayloader`` (linked when the stream's first
    packet arrives) and an RTCP feedback sink (no destination until :meth:`set_feedback`)."""
    rtpbin = make(
        "rtpbin",
        "rtpbin",
        rtp_profile="avpf",
        latency=REPAIR_LATENCY_MS,
        do_retransmission=True,
        do_lost=True,
        drop_on_latency=True,
        autoremove=True,
    )
    feedback_sink = make(
        "multiudpsink", "rtcp_out", clients="", sync=False, async_=False, auto_multicast=False
    )
    receiver = RepairReceiver(rtpbin, feedback_sink, feedback_out=SinkSocket(feedback_sink))
    media_caps = caps(f"{rtp_caps},{FEEDBACK_CAPS}")
    rtx_caps = caps(
        f"application/x-rtp,media=video,clock-rate=90000,encoding-name=RTX,"
        f"payload={RTX_PAYLOAD_TYPE},apt=96"
    )

    fec_caps = caps(f"{FEC_CAPS},payload={FEC_PAYLOAD_TYPE}")
    fec_rtx_caps = caps(
        f"application/x-rtp,media=video,clock-rate=90000,encoding-name=RTX,"
        f"payload={FEC_RTX_PAYLOAD_TYPE},apt={FEC_PAYLOAD_TYPE}"
    )

    def pt_map(_bin: Any, _session: int, pt: int) -> Any:
        if pt == FEC_PAYLOAD_TYPE:
            return fec_caps
        if pt == FEC_RTX_PAYLOAD_TYPE:
            return fec_rtx_caps
        return rtx_caps if pt == RTX_PAYLOAD_TYPE else media_caps

    def fec_decoder(bin_: Any, session: int) -> Any:
        # After the jitter buffer: a packet it gives up on is rebuilt, if it can be, from the
        # FEC packets the storage (before the buffer) kept. The FEC packets stop here.
        decoder = make("rtpulpfecdec", pt=FEC_PAYLOAD_TYPE)
        decoder.set_property("storage", bin_.emit("get-internal-storage", session))
        with receiver._lock:
            receiver.fec_decoders.append(decoder)
        return decoder

    def new_storage(_bin: Any, storage: Any, _session: int) -> None:
        storage.set_property("size-time", FEC_STORAGE_MS * 1_000_000)

    def new_jitterbuffer(_bin: Any, jitterbuffer: Any, _session: int, _ssrc: int) -> None:
        # Ask for a missing packet at once (a reordered one costs a NACK, a wait costs a frame).
        jitterbuffer.set_property("rtx-delay", RTX_DELAY_MS)
        # A gap shows when the next packet arrives: no guessing when a packet is "due" (with
        # no delay, every packet a queue held back a little was asked for again).
        jitterbuffer.set_property("rtx-next-seqnum", False)
        jitterbuffer.set_property("rtx-max-retries", RTX_MAX_RETRIES)
        jitterbuffer.set_property("rtx-retry-timeout", RTX_RETRY_FIRST_MS)
        # Its own floor is the packet spacing: at 5 fps 190 ms, one try per packet.
        jitterbuffer.set_property("rtx-min-retry-timeout", RTX_RETRY_MIN_MS)
        jitterbuffer.get_static_pad("src").add_probe(
            gst().PadProbeType.BUFFER, _follow_round_trip, [0.0]
        )
        reask = attach_early_reask(jitterbuffer)
        with receiver._lock:
            receiver.jitterbuffers.append(jitterbuffer)
            receiver.reasks.append(reask)

    def pad_added(_bin: Any, pad: Any) -> None:
        if not pad.get_name().startswith("recv_rtp_src_"):
            return
        if pad.get_name().endswith(f"_{FEC_PAYLOAD_TYPE}"):
            # The FEC packets, kept by the storage for the decoder: nothing more to do with
            # them (unlinked, their flow error would stop the stream).
            sink = make("fakesink", sync=False, async_=False)
            pipeline.add(sink)
            sink.sync_state_with_parent()
            pad.link(sink.get_static_pad("sink"))
            return
        # A new SSRC is the sender rebuilt (a camera came back): follow it, drop the old.
        sink = depayloader.get_static_pad("sink")
        old = sink.get_peer()
        if old is not None:
            old.unlink(sink)
        pad.link(sink)

    rtpbin.connect("request-pt-map", pt_map)
    rtpbin.connect("request-aux-receiver", _aux_receiver)
    rtpbin.connect("new-jitterbuffer", new_jitterbuffer)
    if fec:
        # Only where the sender was set to send FEC: the decoder sits between the jitter
        # buffer and the depayloader, and measured under load the keyframe request after a
        # cut then came late or not at all.
        rtpbin.connect("new-storage", new_storage)
        rtpbin.connect("request-fec-decoder", fec_decoder)
    rtpbin.connect("pad-added", pad_added)
    source.set_property("caps", media_caps)
    for element in (rtpbin, feedback_sink):
        pipeline.add(element)
    _link(source, "src", rtpbin, "recv_rtp_sink_0")
    _link(rtpbin, "send_rtcp_src_0", feedback_sink, "sink")
    session = rtpbin.emit("get-session", 0)
    session.set_property("rtcp-fraction", FEEDBACK_BYTES_PER_S)
    session.set_property("rtcp-min-interval", FEEDBACK_INTERVAL_NS)
    internal = session.get_property("internal-session")
    receiver.session = internal
    if internal is not None:
        internal.set_property("rtcp-reduced-size", REDUCED_SIZE_FEEDBACK)
    if internal is not None and internal.find_property("twcc-feedback-interval") is not None:
        internal.set_property("twcc-feedback-interval", TRANSPORT_FEEDBACK_INTERVAL_NS)
    if depayloader.find_property("request-keyframe") is not None:
        depayloader.set_property("request-keyframe", True)
        receiver.depayloader_sink = depayloader.get_static_pad("sink")
        receiver.depayloader_sink.add_probe(
            gst().PadProbeType.EVENT_UPSTREAM, _count_keyframe_request, receiver
        )
        depayloader.get_static_pad("src").add_probe(
            gst().PadProbeType.BUFFER, _note_keyframe, receiver
        )
    source.get_static_pad("src").add_probe(gst().PadProbeType.BUFFER, _on_arrival, receiver)
    return receiver


def rtx_retry_ms(rtt_ms: float | None) -> int:
    """The wait before asking again for a missing packet: a round trip and a half (the copy
    asked for is still on its way before that). The jitter buffer's own estimate is at least
    the spacing of the packets, which at 5 fps (frames 200 ms apart) came to 190 ms: one try
    within the budget, and a tenth of the packets lost for good at 10 % loss each way (a
    try fails 19 % of the time)."""
    if rtt_ms is None or rtt_ms <= 0:
        return RTX_RETRY_FIRST_MS
    # Never sooner, however few tries fit: behind a full queue (round trips of 300 ms and
    # more) a try before the first copy could come only adds to the queue.
    return max(RTX_RETRY_MIN_MS, round(1.5 * rtt_ms))


def _follow_round_trip(pad: Any, info: Any, next_at: list[float]) -> Any:
    """Streaming thread, after the jitter buffer (its lock is not held while it pushes): set
    its retry wait from the round trip its retransmissions took, every RTX_RETRY_EVERY_S."""
    now = time.monotonic()
    if now >= next_at[0]:
        next_at[0] = now + RTX_RETRY_EVERY_S
        jitterbuffer = pad.get_parent_element()
        if jitterbuffer is not None:
            ok, rtt_ns = jitterbuffer.get_property("stats").get_uint64("rtx-rtt")
            retry = rtx_retry_ms(rtt_ns / 1e6 if ok else None)
            jitterbuffer.set_property("rtx-retry-timeout", retry)
    return gst().PadProbeReturn.OK


def _count_keyframe_request(pad: Any, info: Any, receiver: RepairReceiver) -> Any:
    event = info.get_event()
    structure = event.get_structure() if event is not None else None
    if structure is None or structure.get_name() != "GstForceKeyUnit":
        return gst().PadProbeReturn.OK
    now = time.monotonic()
    if structure.has_field("asked-again"):
        receiver.keyframe_requests += 1
        return gst().PadProbeReturn.OK
    if not structure.has_field("after-silence") and receiver.asked_at is not None:
        if now - receiver.asked_at < KEYFRAME_ASKED_HOLD_S:
            receiver.keyframe_requests_held += 1
            return gst().PadProbeReturn.DROP
    receiver.keyframe_requests += 1
    receiver.keyframe_asked(now)
    return gst().PadProbeReturn.OK


def _note_keyframe(pad: Any, info: Any, receiver: RepairReceiver) -> Any:
    """Streaming thread, each access unit out of the depayloader: one without the
    DELTA_UNIT flag holds an IDR picture (rtph264depay clears the flag only for an access unit
    with an IDR slice or the SPS/PPS sent with one; after a loss it lets nothing out before an
    IDR slice starts a picture), and pays the keyframe owed."""
    buffer = info.get_buffer()
    if buffer is not None and not buffer.has_flags(gst().BufferFlags.DELTA_UNIT):
        receiver.keyframe_arrived()
    return gst().PadProbeReturn.OK


def _on_arrival(pad: Any, info: Any, receiver: RepairReceiver) -> Any:
    """Streaming thread, each packet as it arrives (before the jitter buffer): the packets
    missing before it asked for at once (:meth:`RepairReceiver.on_media_packet`); a keyframe
    at once when a silence skipped frames past their deadline; and each packet's arrival, a
    retransmission's as its original, for the early asks (:mod:`brasidas.media.reask`). One
    probe a packet: each takes the GIL on the streaming thread."""
    buffer = info.get_buffer()
    header = buffer.extract_dup(0, 12) if buffer is not None else b""
    if len(header) < 8:
        return gst().PadProbeReturn.OK
    now = time.monotonic()
    payload_type = header[1] & 0x7F
    if payload_type == RTX_PAYLOAD_TYPE:
        original = rtx_original_seq(buffer.extract_dup(0, min(buffer.get_size(), RTX_HEADER_READ)))
        if original is not None:
            for follower in receiver.reasks:
                follower.arrived(original, now)
    elif payload_type == MEDIA_PAYLOAD_TYPE:
        seq = int.from_bytes(header[2:4], "big")
        for follower in receiver.reasks:
            follower.arrived(seq, now)
        # No keyframe requests (no depayloader asking): no silence to end.
        silence = receiver.depayloader_sink is not None and receiver.silence.on_packet(
            seq, int.from_bytes(header[4:8], "big"), now
        )
        if len(header) >= 12:
            receiver.on_media_packet(int.from_bytes(header[8:12], "big"), seq, now, silence=silence)
        if receiver.depayloader_sink is None:
            return gst().PadProbeReturn.OK
        if silence:
            receiver.ask_keyframe(now)
            receiver.skip_silence(now)
        else:
            receiver.end_skipping(now)
            receiver.ask_again_if_owed(now)
    elif payload_type == FEC_PAYLOAD_TYPE and len(header) >= 12:
        # In the media's own sequence: not a gap.
        receiver.gaps.on_packet(
            int.from_bytes(header[8:12], "big"), int.from_bytes(header[2:4], "big")
        )
    return gst().PadProbeReturn.OK


def _aux_receiver(rtpbin: Any, session: int) -> Any:
    Gst = gst()
    bin_ = Gst.Bin.new(f"rtx_receive_{session}")
    # Mapped the same way as the sender's: original payload type → retransmission's.
    rtx = make(
        "rtprtxreceive",
        payload_type_map=Gst.Structure.new_from_string(_RTX_PT_MAP),
    )
    bin_.add(rtx)
    bin_.add_pad(Gst.GhostPad.new(f"src_{session}", rtx.get_static_pad("src")))
    bin_.add_pad(Gst.GhostPad.new(f"sink_{session}", rtx.get_static_pad("sink")))
    return bin_


def _link(upstream: Any, src: str, downstream: Any, sink: str) -> None:
    from brasidas.media.gst import MediaError

    if not upstream.link_pads(src, downstream, sink):
        raise MediaError(
            f"cannot link {upstream.get_name()}.{src} to {downstream.get_name()}.{sink}"
        )
