"""Transport-wide congestion feedback read packet by packet (sans-IO).

The receivers' rtpsession reports each packet's arrival time in RTCP transport-wide feedback
(draft-holmer-rmcat-transport-wide-cc-extensions-01: RTPFB, FMT 15) about every 30 ms. The
sender's rtpsession only offers an average of it over 300 ms (``twcc-stats``), which saw a
capacity drop 0.21-0.26 s late. Here each feedback is parsed (:func:`parse_feedback`) and
every reported packet is matched to its own send time and size (:class:`SendHistory`, fed
with the transport-wide sequence number read from each packet sent: :func:`transport_seq`).
:class:`QueueDetector` then sees the link's queue within a feedback or two:

- the newest packet's one-way delay over the smallest of the last seconds (the clocks'
  offset cancels): how long it waited in a queue;
- the rate at which the last 100 ms of packets arrived: while a queue holds packets the link
  delivers at its capacity, whatever was sent.

A queue over :data:`QUEUE_MS` fed faster than the link delivers (:data:`DELIVERED_SHARE`),
in two feedbacks running, is a link over its capacity. A keyframe's burst queues too, but
drains at the link's full rate; a forwarder's stall queues, but its backlog then arrives at
once; random loss queues nothing.
"""

from __future__ import annotations

import collections
from dataclasses import dataclass, field

RTCP_RTPFB = 205
TWCC_FMT = 15
"""RTCP transport-layer feedback, format 15: transport-wide congestion control."""
REFERENCE_TIME_US = 64_000
"""The feedback's reference time counts in 64 ms."""
DELTA_US = 250
"""Receive deltas count in 250 µs."""

STATUS_NOT_RECEIVED = 0
STATUS_SMALL_DELTA = 1
STATUS_LARGE_DELTA = 2


class FeedbackError(ValueError):
    """A transport-wide feedback that cannot be read (truncated or not to the format)."""


@dataclass(frozen=True)
class TransportFeedback:
    """One transport-wide feedback: the packets it covers, from ``base_seq`` on."""

    base_seq: int
    reference_time: int
    """24 bits, in :data:`REFERENCE_TIME_US`: the receiver's own clock, unknown base."""
    feedback_count: int
    arrivals_us: tuple[int | None, ...]
    """Each packet's arrival (µs on the receiver's clock), None when not received; packet
    ``i`` is sequence number ``(base_seq + i) & 0xFFFF``."""

    def packets(self) -> list[tuple[int, int | None]]:
        """``(sequence number, arrival µs or None)`` of each packet covered."""
        return [((self.base_seq + i) & 0xFFFF, at) for i, at in enumerate(self.arrivals_us)]


def parse_feedback(fci: bytes) -> TransportFeedback:
    """The feedback control information of one transport-wide feedback (after the RTCP
    header and the two SSRCs): base sequence number, packet status count, reference time,
    feedback packet count, status chunks, receive deltas. Raises :class:`FeedbackError`."""
    if len(fci) < 8:
        raise FeedbackError(f"{len(fci)} bytes: shorter than the 8-byte header")
    base = int.from_bytes(fci[0:2], "big")
    count = int.from_bytes(fci[2:4], "big")
    reference = int.from_bytes(fci[4:7], "big")
    feedback_count = fci[7]
    if count == 0:
        raise FeedbackError("no packet status")
    statuses: list[int] = []
    at = 8
    while len(statuses) < count:
        if at + 2 > len(fci):
            raise FeedbackError(f"truncated in the status chunks ({len(statuses)} of {count})")
        chunk = int.from_bytes(fci[at : at + 2], "big")
        at += 2
        if not chunk & 0x8000:  # run length: one status, 13-bit run
            symbol, run = (chunk >> 13) & 0x3, chunk & 0x1FFF
            if symbol == 3 or run == 0:
                raise FeedbackError(f"run-length chunk {chunk:#06x}")
            statuses.extend([symbol] * run)
        elif not chunk & 0x4000:  # status vector of 14 one-bit symbols
            statuses.extend((chunk >> shift) & 0x1 for shift in range(13, -1, -1))
        else:  # status vector of 7 two-bit symbols
            symbols = [(chunk >> shift) & 0x3 for shift in range(12, -1, -2)]
            if 3 in symbols[: count - len(statuses)]:
                raise FeedbackError(f"reserved symbol in chunk {chunk:#06x}")
            statuses.extend(symbols)
    del statuses[count:]  # a last vector may cover more than the count
    arrivals: list[int | None] = []
    clock = reference * REFERENCE_TIME_US
    for status in statuses:
        if status == STATUS_NOT_RECEIVED:
            arrivals.append(None)
            continue
        size = 1 if status == STATUS_SMALL_DELTA else 2
        if at + size > len(fci):
            raise FeedbackError(f"truncated in the receive deltas ({len(arrivals)} of {count})")
        clock += int.from_bytes(fci[at : at + size], "big", signed=size == 2) * DELTA_US
        at += size
        arrivals.append(clock)
    return TransportFeedback(base, reference, feedback_count, tuple(arrivals))


def transport_seq(packet: bytes, extension_id: int) -> int | None:
    """The transport-wide sequence number in an RTP packet's header extension (one- or
    two-byte form, RFC 8285), or None."""
    if len(packet) < 12 or packet[0] >> 6 != 2 or not packet[0] & 0x10:
        return None
    start = 12 + (packet[0] & 0x0F) * 4
    if len(packet) < start + 4:
        return None
    profile = int.from_bytes(packet[start : start + 2], "big")
    end = min(len(packet), start + 4 + 4 * int.from_bytes(packet[start + 2 : start + 4], "big"))
    at = start + 4
    one_byte = profile == 0xBEDE
    if not one_byte and profile & 0xFFF0 != 0x1000:
        return None
    while at < end:
        if one_byte:
            ident, length = packet[at] >> 4, (packet[at] & 0x0F) + 1
            if ident == 0:  # padding
                at += 1
                continue
            if ident == 15:
                return None
            at += 1
        else:
            if packet[at] == 0:
                at += 1
                continue
            if at + 2 > end:
                return None
            ident, length = packet[at], packet[at + 1]
            at += 2
        if ident == extension_id and length >= 2 and at + 2 <= end:
            return int.from_bytes(packet[at : at + 2], "big")
        at += length
    return None


class SendHistory:
    """When each packet left and its size, by transport-wide sequence number (one slot per
    16-bit number: the streaming thread writes a slot, the feedback's thread reads one;
    neither iterates what the other changes)."""

    def __init__(self) -> None:
        self._slots: list[tuple[float, int] | None] = [None] * 0x10000

    def on_sent(self, seq: int, size: int, now: float) -> None:
        slot = self._slots[seq & 0xFFFF]
        if slot is not None and 0 <= now - slot[0] <= HISTORY_S:
            return  # a retransmission carries its original's number: the first send counts
        self._slots[seq & 0xFFFF] = (now, size)

    def get(self, seq: int, now: float) -> tuple[float, int] | None:
        """``(sent at, bytes)``; None if unknown or from a sequence number's earlier round."""
        slot = self._slots[seq & 0xFFFF]
        if slot is None or not 0 <= now - slot[0] <= HISTORY_S:
            return None
        return slot

    def sent_kbps(self, newest_seq: int, span_s: float, now: float) -> float:
        """What left in the ``span_s`` before packet ``newest_seq`` (it included), kbit/s."""
        newest = self.get(newest_seq, now)
        if newest is None:
            return 0.0
        total = 0
        for back in range(0x1000):
            slot = self.get(newest_seq - back, now)
            if slot is None or newest[0] - slot[0] > span_s:
                break
            total += slot[1]
        return total * 8 / 1000 / span_s


HISTORY_S = 2.0
"""A send time this old is forgotten (a report about it is too late to act on)."""
BASELINE_S = 5.0
"""The smallest one-way delay of this long is the link without a queue."""
QUEUE_MS = 30.0
"""A packet that waited longer than this: a queue (a 2 Mbit/s link at 1.5 Mbit/s with a
keyframe queues its last packets 40-80 ms, drained at the link's full rate; 10 % random
loss with retransmission queues nothing)."""
CAPACITY_SPAN_S = 0.1
"""The link's delivery rate is read over the packets that arrived in this long."""
CAPACITY_PACKETS = 3
CAPACITY_MIN_SPAN_S = 0.03
"""... at least this many packets over at least this long (fewer read the bucket's burst)."""
SENT_SPAN_S = 0.3
"""What the sender sent: over this long before the newest packet reported."""
DELIVERED_SHARE = 0.75
"""A queue that the link drains at under this share of what is sent grows."""
CONFIRM_GAP_S = 0.02
"""Two feedbacks showing the overuse, at least this far apart (not one RTCP compound)."""
QUEUE_FALLING_MS = 10.0
"""The second may show a queue this much shorter at most (a stall's backlog drains fast)."""


@dataclass(frozen=True)
class QueueOveruse:
    """A link over its capacity, seen in the feedback at ``at``."""

    queue_ms: float
    capacity_kbps: float
    """What the link delivered while the queue held packets."""
    sent_kbps: float
    at: float
    newest_sent_at: float
    """When the newest packet reported left (what was sent after a cut is not yet in it)."""


@dataclass
class FeedbackCounters:
    feedbacks: int = 0
    malformed: int = 0
    """Feedbacks that could not be read: counted and dropped."""
    packets_reported: int = 0
    packets_lost: int = 0
    unknown: int = 0
    """Packets reported that the history does not know (too old, or not sent by us)."""


@dataclass
class _Receiver:
    """One receiver's clock and recent arrivals."""

    reference: int | None = None
    reference_round: int = 0
    baseline: collections.deque[tuple[int, float]] = field(default_factory=collections.deque)
    """(second, smallest one-way offset in it), for :data:`BASELINE_S`."""
    arrivals: collections.deque[tuple[float, int]] = field(default_factory=collections.deque)
    """(arrival s on its clock, bytes) of recently received packets."""
    newest_seq: int | None = None
    candidate: tuple[float, float] | None = None
    """(when, queue ms) of a feedback that showed the overuse, not yet confirmed."""


RECEIVERS = 8
"""Receivers tracked at once (each feedback names its sender; the oldest is forgotten)."""


class QueueDetector:
    """The link's queue, from each transport-wide feedback (sans-IO: ``now`` is passed in,
    the sender's clock, the one :class:`SendHistory` was written with)."""

    def __init__(self) -> None:
        self.counters = FeedbackCounters()
        self.queue_ms = 0.0
        """The newest packet's wait in the link's queue (the latest feedback's)."""
        self.capacity_kbps = 0.0
        """What the link delivered in the latest feedback's last 100 ms."""
        self.sent_kbps = 0.0
        """What was sent in the 300 ms before the latest feedback's newest packet."""
        self._receivers: dict[int, _Receiver] = {}

    def on_feedback(
        self, fci: bytes, sender_ssrc: int, history: SendHistory, now: float
    ) -> QueueOveruse | None:
        """One feedback from receiver ``sender_ssrc`` at ``now``: an overuse when this one
        confirms it, else None. A malformed one is counted and dropped."""
        try:
            feedback = parse_feedback(fci)
        except FeedbackError:
            self.counters.malformed += 1
            return None
        self.counters.feedbacks += 1
        receiver = self._receivers.pop(sender_ssrc, None) or _Receiver()
        self._receivers[sender_ssrc] = receiver  # newest last
        if len(self._receivers) > RECEIVERS:
            del self._receivers[next(iter(self._receivers))]
        return self._read(receiver, feedback, history, now)

    def _read(
        self, receiver: _Receiver, feedback: TransportFeedback, history: SendHistory, now: float
    ) -> QueueOveruse | None:
        round_us = self._unwrapped_round(receiver, feedback.reference_time)
        newest: tuple[int, float, float] | None = None
        """(seq, sent at, one-way offset) of the newest packet sent that arrived."""
        for seq, arrival_us in feedback.packets():
            self.counters.packets_reported += 1
            if arrival_us is None:
                self.counters.packets_lost += 1
                continue
            sent = history.get(seq, now)
            if sent is None:
                self.counters.unknown += 1
                continue
            arrival = (arrival_us + round_us) / 1e6
            offset = arrival - sent[0]
            _note_baseline(receiver.baseline, sent[0], offset)
            receiver.arrivals.append((arrival, sent[1]))
            # Only packets newer than any reported before tell the queue now (a
            # retransmission, reported under its original's number, left long after it).
            fresh = receiver.newest_seq is None or 0 < (seq - receiver.newest_seq) & 0xFFFF < 0x8000
            if fresh and (newest is None or sent[0] >= newest[1]):
                newest = (seq, sent[0], offset)
        if newest is None:
            return None
        receiver.newest_seq = newest[0]
        latest = max(at for at, _ in receiver.arrivals)
        while receiver.arrivals and latest - receiver.arrivals[0][0] > CAPACITY_SPAN_S:
            receiver.arrivals.popleft()
        seq, _, offset = newest
        self.queue_ms = max(0.0, (offset - min(m for _, m in receiver.baseline)) * 1000)
        self.capacity_kbps = _delivered_kbps(receiver.arrivals)
        sent_kbps = history.sent_kbps(seq, SENT_SPAN_S, now)
        self.sent_kbps = sent_kbps
        overused = self.queue_ms > QUEUE_MS and 0 < self.capacity_kbps < DELIVERED_SHARE * sent_kbps
        if not overused:
            receiver.candidate = None
            return None
        candidate = receiver.candidate
        if candidate is None or now - candidate[0] < CONFIRM_GAP_S:
            receiver.candidate = candidate or (now, self.queue_ms)
            return None
        if self.queue_ms < candidate[1] - QUEUE_FALLING_MS:
            receiver.candidate = (now, self.queue_ms)  # draining: no confirmation yet
            return None
        receiver.candidate = None
        return QueueOveruse(self.queue_ms, self.capacity_kbps, sent_kbps, now, newest[1])

    @staticmethod
    def _unwrapped_round(receiver: _Receiver, reference: int) -> int:
        """µs to add for the 24-bit reference time's wrap (every ~12 days of the receiver's
        clock); a jump back of over half its range is a wrap, else taken as is."""
        last = receiver.reference
        if last is not None and last - reference > 0x800000:
            receiver.reference_round += 1
        elif last is not None and reference - last > 0x800000:
            receiver.reference_round -= 1  # a late feedback from before the wrap
        receiver.reference = reference
        return receiver.reference_round * 0x1000000 * REFERENCE_TIME_US


def _note_baseline(
    baseline: collections.deque[tuple[int, float]], sent: float, offset: float
) -> None:
    second = int(sent)
    if baseline and baseline[-1][0] == second:
        if offset < baseline[-1][1]:
            baseline[-1] = (second, offset)
    else:
        baseline.append((second, offset))
    while baseline and second - baseline[0][0] > BASELINE_S:
        baseline.popleft()


def _delivered_kbps(arrivals: collections.deque[tuple[float, int]]) -> float:
    """The rate the packets arrived at (the first's bytes arrived before the span began);
    0 when too few to tell."""
    if len(arrivals) < CAPACITY_PACKETS:
        return 0.0
    ordered = sorted(arrivals)
    span = ordered[-1][0] - ordered[0][0]
    if span < CAPACITY_MIN_SPAN_S:
        return 0.0
    return sum(size for _, size in ordered[1:]) * 8 / 1000 / span
