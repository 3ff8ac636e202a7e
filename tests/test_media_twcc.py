"""Transport-wide feedback read packet by packet: the parser (feedback built from the draft's
format) and the queue detector on a simulated link with a stepped clock (sans-IO)."""

from __future__ import annotations

import random
import struct

import pytest

from brasidas.media.twcc import (
    DELTA_US,
    REFERENCE_TIME_US,
    FeedbackError,
    QueueDetector,
    SendHistory,
    parse_feedback,
    transport_seq,
)


def _header(base: int, count: int, reference: int, fb_count: int = 0) -> bytes:
    return struct.pack("!HH", base, count) + reference.to_bytes(3, "big") + bytes([fb_count])


def _two_bit_vector(symbols: list[int]) -> bytes:
    chunk = 0xC000
    for i, symbol in enumerate(symbols):
        chunk |= symbol << (12 - 2 * i)
    return struct.pack("!H", chunk)


def build_feedback(base: int, arrivals_us: list[int | None], reference: int) -> bytes:
    """A feedback as the draft lays it out: two-bit status vectors, one- or two-byte deltas
    from the reference time, padded to 32 bits."""
    symbols: list[int] = []
    deltas = b""
    clock = reference * REFERENCE_TIME_US
    for at in arrivals_us:
        if at is None:
            symbols.append(0)
            continue
        delta = (at - clock) // DELTA_US
        clock += delta * DELTA_US
        if 0 <= delta <= 255:
            symbols.append(1)
            deltas += bytes([delta])
        else:
            symbols.append(2)
            deltas += struct.pack("!h", delta)
    chunks = b"".join(_two_bit_vector(symbols[i : i + 7]) for i in range(0, len(symbols), 7))
    body = _header(base, len(arrivals_us), reference) + chunks + deltas
    return body + bytes(-len(body) % 4)


def test_a_run_length_chunk_and_one_byte_deltas() -> None:
    # 3 packets received, small deltas 4, 8, 0 (in 250 µs), reference 10 (in 64 ms), padded.
    fci = _header(100, 3, 10, fb_count=7) + struct.pack("!H", 0x2003) + bytes([4, 8, 0, 0])
    feedback = parse_feedback(fci)
    start = 10 * 64_000
    assert feedback.feedback_count == 7
    assert feedback.packets() == [(100, start + 1000), (101, start + 3000), (102, start + 3000)]


def test_a_one_bit_vector_with_a_loss_and_symbols_past_the_count() -> None:
    # 14 one-bit symbols 1,0,1,1,0... but the count says 4: the rest is ignored.
    chunk = 0x8000 | (0b10110000000000)
    fci = _header(7, 4, 0) + struct.pack("!H", chunk) + bytes([1, 2, 3, 0, 0, 0])
    arrivals = parse_feedback(fci).arrivals_us
    assert arrivals == (250, None, 750, 1500)


def test_two_byte_deltas_go_back_in_time_and_the_sequence_wraps() -> None:
    arrivals: list[int | None] = [1_000_000, 1_200_000, None, 1_100_000, 1_100_250]
    fci = build_feedback(65534, arrivals, reference=15)
    feedback = parse_feedback(fci)
    assert [seq for seq, _ in feedback.packets()] == [65534, 65535, 0, 1, 2]
    assert feedback.arrivals_us == tuple(arrivals)


@pytest.mark.parametrize(
    ("fci", "why"),
    [
        (b"\x00\x01\x00\x03\x00\x00", "shorter than the 8-byte header"),
        (_header(0, 0, 0), "no packet status"),
        (_header(0, 20, 0) + struct.pack("!H", 0x200A), "status chunks"),
        (_header(0, 3, 0) + struct.pack("!H", 0x2003) + bytes([1, 2]), "receive deltas"),
        (_header(0, 3, 0) + struct.pack("!H", 0x4003 | 0x2000), "run-length chunk"),
        (_header(0, 3, 0) + struct.pack("!H", 0x2000), "run-length chunk"),
        (_header(0, 2, 0) + _two_bit_vector([1, 3]) + bytes([1, 1]), "reserved symbol"),
        (_header(0, 2, 0) + _two_bit_vector([2, 2]) + bytes([0, 1, 0]), "receive deltas"),
    ],
)
def test_a_truncated_or_corrupt_feedback_is_refused_and_counted(fci: bytes, why: str) -> None:
    with pytest.raises(FeedbackError, match=why):
        parse_feedback(fci)
    detector = QueueDetector()
    assert detector.on_feedback(fci, 1, SendHistory(), 0.0) is None
    assert detector.counters.malformed == 1
    assert detector.counters.feedbacks == 0


def test_random_bytes_never_raise_anything_but_a_feedback_error() -> None:
    rng = random.Random(28)
    for _ in range(2000):
        fci = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 40)))
        try:
            parse_feedback(fci)
        except FeedbackError:
            pass


def test_the_transport_number_is_read_from_either_extension_form() -> None:
    rtp = bytes([0x90, 96]) + bytes(10)
    one_byte = rtp + b"\xbe\xde\x00\x03" + b"\x17" + bytes(8) + b"\x21\x12\x34" + b"\x00"
    assert transport_seq(one_byte, 2) == 0x1234
    two_byte = rtp + b"\x10\x00\x00\x02" + b"\x02\x02\xab\xcd" + bytes(4)
    assert transport_seq(two_byte, 2) == 0xABCD
    assert transport_seq(rtp, 2) is None  # the extension bit set, nothing after the header
    assert transport_seq(bytes([0x80, 96]) + bytes(10), 2) is None


class Link:
    """A token-bucket link with a queue of at most ``queue_s`` of waiting, random loss,
    and the receiver's feedback every 25 ms (as the station's rtpsession is set to)."""

    def __init__(self, kbps: float, *, loss: float = 0.0, queue_s: float = 0.1) -> None:
        self.kbps = kbps
        self.loss = loss
        self.queue_s = queue_s
        self.free_at = 0.0
        self.delay = 0.005
        self.rng = random.Random(5)
        self.arrivals: list[tuple[int, float | None]] = []
        """(seq, arrival) in the receiver's clock (an offset from the sender's: 1000 s)."""
        self.stall_until = 0.0

    def send(self, seq: int, size: int, now: float) -> None:
        start = max(now, self.free_at, self.stall_until)
        if start - now > self.queue_s or self.rng.random() < self.loss:
            self.arrivals.append((seq, None))
            return
        self.free_at = start + size * 8 / (self.kbps * 1000)
        self.arrivals.append((seq, 1000.0 + self.free_at + self.delay))

    def feedback(self, now: float) -> bytes | None:
        """Packets arrived by ``now`` (receiver clock), in sequence order, as one feedback."""
        due = [(s, a) for s, a in self.arrivals if a is None or a - 1000.0 <= now]
        if not due or all(a is None for _, a in due):
            return None
        last = max(i for i, (_, a) in enumerate(due) if a is not None)
        reported = due[: last + 1]
        self.arrivals = self.arrivals[len(reported) :]  # due ones come first (in order)
        first = min(a for _, a in reported if a is not None)
        reference = int(first * 1e6) // REFERENCE_TIME_US
        return build_feedback(
            reported[0][0],
            [None if a is None else round(a * 1e6) for _, a in reported],
            reference,
        )


def run(
    link: Link,
    seconds: float,
    *,
    drop_at: float | None = None,
    keyframe_every_s: float = 1.0,
    stall_at: float | None = None,
    first_seq: int = 0,
) -> list[float]:
    """30 fps at 1.5 Mbit/s (a 20 kB keyframe each second), sent and fed back on a stepped
    clock; when the detector saw an overuse."""
    detector = QueueDetector()
    history = SendHistory()
    seq = first_seq
    seen: list[float] = []
    step = 0.001
    for tick in range(int(seconds / step)):
        now = tick * step
        if drop_at is not None and abs(now - drop_at) < step / 2:
            link.kbps = 500
        if stall_at is not None and abs(now - stall_at) < step / 2:
            link.stall_until = now + 0.08
        if tick % 33 == 0:  # a frame: its packets leave at once
            keyframe = tick % round(keyframe_every_s / step) < 33
            size = 20_000 if keyframe else 5_500
            for _ in range(-(-size // 1200)):
                history.on_sent(seq & 0xFFFF, 1200, now)
                link.send(seq & 0xFFFF, 1200, now)
                seq += 1
        if tick % 25 == 0:
            fci = link.feedback(now)
            if fci is not None and detector.on_feedback(fci, 7, history, now) is not None:
                seen.append(now)
    return seen


def test_a_capacity_drop_is_seen_within_a_hundred_milliseconds() -> None:
    seen = run(Link(2000), 3.0, drop_at=2.0)
    assert seen, "never seen"
    assert 2.0 < seen[0] <= 2.11, seen  # the 500 kbit/s queue passes 30 ms at ~2.08


def test_keyframes_on_a_link_that_keeps_up_are_no_overuse_across_the_sequence_wrap() -> None:
    assert run(Link(2000), 4.0, first_seq=65000) == []


def test_ten_percent_random_loss_is_no_overuse() -> None:
    assert run(Link(10_000, loss=0.10), 4.0) == []


def test_a_forwarder_stalling_80_ms_is_no_overuse() -> None:
    assert run(Link(10_000), 3.0, stall_at=1.5) == []
    assert run(Link(2000), 3.0, stall_at=1.5) == []


def test_each_receiver_is_read_on_its_own_clock() -> None:
    history = SendHistory()
    detector = QueueDetector()
    for seq in range(12):
        history.on_sent(seq, 1200, seq * 0.01)
    # Receiver 1's clock is 5 s ahead of receiver 2's: each one's smallest delay is its own.
    for ssrc, offset_us in ((1, 5_000_000), (2, 0)):
        arrivals: list[int | None] = [offset_us + seq * 10_000 + 3000 for seq in range(12)]
        fci = build_feedback(0, arrivals, reference=offset_us // REFERENCE_TIME_US)
        assert detector.on_feedback(fci, ssrc, history, 0.2) is None
        assert detector.queue_ms < 1.0
    assert detector.counters.packets_reported == 24
    assert detector.counters.unknown == 0
