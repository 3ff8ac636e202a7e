"""A missing packet asked for once more, a round trip after its first NACK.

The receiver's jitter buffer asks for a missing packet at once, then again every
:data:`~brasidas.media.repair.RTX_RETRY_MIN_MS` (33 ms) at the least: a loaded machine's
stall must not use every try up at once. But on a link losing 10 % each way the NACK or its
retransmission is lost for ~19 % of the missing packets, and each of those frames came 33 ms
late (g2g p95 40 ms against 8 on a clean link). Here such a packet is asked for once more as
soon as its retransmission is overdue: the longest of the recent first-round repairs
(first ask → packet), plus a margin. Once only: the jitter buffer's own, slower tries still
follow, so a stall costs at most one retransmission more per missing packet.

:class:`EarlyReask` decides (sans-IO); :func:`attach_early_reask` follows one jitter buffer's
requests and times the extra ask on the GStreamer clock's own thread; the arrivals come from
the receiver's one probe on each packet (a second probe per packet cost ~1 ms of
glass-to-glass at the median: each takes the GIL on the streaming thread).
"""

from __future__ import annotations

import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from brasidas.media.gst import gst

REASK_FLOOR_S = 0.005
"""Never sooner than this after the first ask (a NACK leaves 1.5 ms after its gap shows at
the median, its retransmission comes a millisecond later: ~3 ms on a short link)."""
REASK_MARGIN_S = 0.003
"""Beyond the longest recent first-round repair: its scheduling noise."""
REASK_SAMPLES = 16
"""First-round repairs the wait is taken from (the longest of them)."""
REASK_MIN_SAMPLES = 4
"""No early ask before this many repairs were timed (a new stream's round trip is unknown)."""
REASK_BEFORE_RETRY_S = 0.005
"""No early ask unless it comes at least this much before the jitter buffer's own retry
(on a long round trip the two would come together: one retransmission for nothing)."""
PENDING_MAX = 512
"""Missing packets followed at most (the oldest is forgotten first)."""
PENDING_FOR_S = 1.0
"""A packet never repaired is forgotten this long after its first ask."""
AT_ONCE_KEPT = 64
"""Packets asked for at once that are remembered until the jitter buffer asks (it asks
within milliseconds, or not at all when the repair came first)."""


@dataclass
class EarlyReask:
    """Sans-IO: the jitter buffer's asks and the packets' arrivals (sequence number, time in
    seconds), and when to ask for a packet once more."""

    samples: deque[float] = field(default_factory=lambda: deque(maxlen=REASK_SAMPLES))
    """First-round repairs: first ask → packet, with no other ask in between."""
    pending: dict[int, tuple[float, bool]] = field(default_factory=dict)
    """Sequence number → (first asked at, asked again since)."""
    reasked: int = 0

    def wait(self, retry_s: float) -> float | None:
        """After a first ask, how long until the early one, or None: none (too few repairs
        timed, or the jitter buffer's own retry, ``retry_s`` after its first ask, comes as
        soon)."""
        if len(self.samples) < REASK_MIN_SAMPLES:
            return None
        wait = max(REASK_FLOOR_S, max(self.samples) + REASK_MARGIN_S)
        return wait if wait + REASK_BEFORE_RETRY_S <= retry_s else None

    def on_asked(self, seq: int, retry: int, now: float, retry_s: float) -> float | None:
        """The jitter buffer asked for ``seq`` (its ``retry``-th time, from 0): the wait until
        the early ask, or None."""
        entry = self.pending.get(seq)
        if entry is not None or retry > 0:
            # Its own retry: the packet's repair is no longer a first-round one, and asked
            # again already.
            if entry is not None:
                self.pending[seq] = (entry[0], True)
            return None
        self._forget(now)
        self.pending[seq] = (now, False)
        return self.wait(retry_s)

    def on_arrived(self, seq: int, now: float) -> None:
        """A packet (or a copy of it, or its retransmission) reached the receiver."""
        entry = self.pending.pop(seq, None)
        if entry is not None and not entry[1]:
            self.samples.append(now - entry[0])

    def due(self, seq: int) -> bool:
        """The early ask's time for ``seq`` has come: True if it is still missing and was not
        asked for again since (then it counts as asked)."""
        entry = self.pending.get(seq)
        if entry is None or entry[1]:
            return False
        self.pending[seq] = (entry[0], True)
        self.reasked += 1
        return True

    def _forget(self, now: float) -> None:
        # In the order first asked: the oldest first.
        while self.pending:
            seq, (asked, _) = next(iter(self.pending.items()))
            if now - asked < PENDING_FOR_S and len(self.pending) < PENDING_MAX:
                return
            del self.pending[seq]


_REQUEST = "GstRTPRetransmissionRequest"
_OURS = "early-reask"
"""Marks the early ask's request (its copy of the jitter buffer's own): not followed again."""


@dataclass
class ReaskFollower:
    """One jitter buffer's :class:`EarlyReask`, fed from the GStreamer threads."""

    reask: EarlyReask
    sink: Any
    """The jitter buffer's sink pad: the asks go upstream from it."""
    lock: threading.Lock = field(default_factory=threading.Lock)
    """The jitter buffer's timer thread, the streaming thread and the clock's thread."""

    at_once: dict[int, float] = field(default_factory=dict)
    """Packets the receiver asked for the moment their gap arrived → when (oldest first)."""
    copies: bool = False
    """The link is lossy: the jitter buffer's own first ask for such a packet goes too."""
    copied: int = 0

    def arrived(self, seq: int, now: float) -> None:
        """Streaming thread: a media packet (or a retransmission of it) came in."""
        if self.reask.pending:  # read without the lock: at worst one packet's check is late
            with self.lock:
                self.reask.on_arrived(seq, now)

    def asked_at_once(self, seqs: list[int], now: float) -> None:
        """Streaming thread: the receiver asked for ``seqs`` itself at ``now``."""
        with self.lock:
            for seq in seqs:
                self.at_once.pop(seq, None)
                self.at_once[seq] = now
            while len(self.at_once) > AT_ONCE_KEPT:
                del self.at_once[next(iter(self.at_once))]

    def asked_first_at(self, seq: int) -> float | None:
        """Under the lock: when the receiver itself asked for ``seq``, if it did (the jitter
        buffer's first ask then repeats it)."""
        return self.at_once.pop(seq, None)


def rtx_original_seq(data: bytes) -> int | None:
    """The original sequence number an RFC 4588 retransmission (``data``, from its RTP
    header on) carries; None if it is cut short."""
    if len(data) < 12:
        return None
    offset = 12 + 4 * (data[0] & 0x0F)
    if data[0] & 0x10:  # a header extension (the transport-wide sequence number's)
        if len(data) < offset + 4:
            return None
        offset += 4 + 4 * int.from_bytes(data[offset + 2 : offset + 4], "big")
    if len(data) < offset + 2:
        return None
    return int.from_bytes(data[offset : offset + 2], "big")


RTX_HEADER_READ = 64
"""Bytes of a retransmission read to find its original sequence number (a header, its
CSRCs and the transport-wide extension are well within)."""


def attach_early_reask(jitterbuffer: Any) -> ReaskFollower:
    """Follow ``jitterbuffer``'s retransmission requests and ask once more early; the
    packets' arrivals come from the receiver's own probe (:meth:`ReaskFollower.arrived`)."""
    follower = ReaskFollower(EarlyReask(), jitterbuffer.get_static_pad("sink"))
    follower.sink.add_probe(gst().PadProbeType.EVENT_UPSTREAM, _on_request, follower)
    return follower


def _on_request(pad: Any, info: Any, follower: ReaskFollower) -> Any:
    """The jitter buffer's timer thread: a request goes upstream (to become a NACK)."""
    Gst = gst()
    event = info.get_event()
    structure = event.get_structure() if event is not None else None
    if structure is None or structure.get_name() != _REQUEST or structure.has_field(_OURS):
        return Gst.PadProbeReturn.OK
    ok_seq, seq = structure.get_uint("seqnum")
    ok_retry, retry = structure.get_uint("retry")
    if not ok_seq:
        return Gst.PadProbeReturn.OK
    # Its own retry's wait (ms), as it stands (the property would take its lock, held here).
    ok_every, every_ms = structure.get_uint("frequency")
    retry_s = every_ms / 1000 if ok_every else 0.0
    first = not ok_retry or retry == 0
    now = time.monotonic()
    with follower.lock:
        # Timed from the first ask that went, the receiver's own when it asked at once (the
        # jitter buffer's comes ~1.5 ms later, more on a loaded machine).
        asked_at = follower.asked_first_at(seq) if first else None
        repeat = asked_at is not None
        first_at = asked_at if asked_at is not None else now
        wait = follower.reask.on_asked(seq, 0 if first else retry, first_at, retry_s)
        if repeat and follower.copies:
            follower.copied += 1
    if wait is not None:
        again = structure.copy()
        again.set_value(_OURS, True)
        clock = Gst.SystemClock.obtain()
        delay = max(0.0, wait - (now - first_at))
        at = clock.new_single_shot_id(clock.get_time() + round(delay * 1e9))
        Gst.Clock.id_wait_async(at, _ask_again, (follower, seq, again))
    if repeat and not follower.copies:
        return Gst.PadProbeReturn.DROP  # asked at once already; its retries still go
    return Gst.PadProbeReturn.OK


def _ask_again(clock: Any, at: int, clock_id: Any, data: tuple[ReaskFollower, int, Any]) -> bool:
    """The clock's thread: the request again, if the packet is still missing."""
    follower, seq, request = data
    with follower.lock:
        due = follower.reask.due(seq)
    if due:
        Gst = gst()
        follower.sink.push_event(Gst.Event.new_custom(Gst.EventType.CUSTOM_UPSTREAM, request))
    return True
