"""The velocity stream's ``$PVEL`` sentence (seed ch. 11 §3.1), sans-IO.

One UDP datagram carries one NMEA-0183 style sentence::

    $PVEL,<count>,<x>,<z>[,<sent>][,<tag>]*<checksum>

``count`` is an unsigned integer that increases with every sentence a sender emits, so the
receiver can drop late and duplicated datagrams. ``x`` (linear) and ``z`` (angular) are signed
decimals with 5 digits after the point, each in [-1, 1]. ``checksum`` is the XOR of every
character between ``$`` and ``*``, as two uppercase hex digits. ``sent`` (optional, 1-8
decimal digits) is when the sentence was sent, in integer milliseconds of the *receiver's*
monotonic clock as the sender estimates it (stations estimate the offset from their
heartbeats, NTP-style), modulo 10⁸ (27.8 hours: the sentence stays within the seed's 64 bytes;
:func:`age_ms` undoes the wrap): the platform knows each packet's age on arrival, without
synchronized clocks. A sentence without it (an older sender) has no known age. With access control on,
``tag`` is a truncated HMAC-SHA256 (8 bytes, 16 hex digits) over the session id, the count,
both values and the send time (when present) as sent, keyed by the session key, so only the
session that holds the manual override can move the robot, a packet replayed from another
session does not verify, and nobody on the path can make an old packet look fresh.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from enum import Enum

from brasidas import security

TALKER = "PVEL"
TAG_BYTES = 8
MAX_COUNT = 2**32 - 1
"""Counts wrap nowhere: at 500 Hz this lasts three months of continuous driving."""
_HEX = frozenset(b"0123456789ABCDEFabcdef")
SENT_MODULUS = 10**8
"""``sent`` is the send time in ms modulo this: at most 8 digits, never 16 (a tag is told
apart by its length)."""
MAX_DATAGRAM = 128
"""The longest valid sentence is about 70 bytes; anything much longer is not ours."""

_BODY = re.compile(
    r"PVEL,(?P<count>\d{1,10}),"
    r"(?P<x>[+-]?\d{1,6}(?:\.\d{1,8})?),"
    r"(?P<z>[+-]?\d{1,6}(?:\.\d{1,8})?)"
    r"(?:,(?P<sent>\d{1,8}))?"
    r"(?:,(?P<tag>[0-9A-Fa-f]{16}))?"  # TAG_BYTES in hex
)


class DropReason(Enum):
    """Why a datagram did not become a velocity. Every value is a telemetry counter."""

    MALFORMED = "malformed"
    BAD_CHECKSUM = "bad_checksum"
    OUT_OF_RANGE = "out_of_range"
    OUT_OF_ORDER = "out_of_order"
    """Count not newer than the last accepted one: late, duplicated or replayed."""
    NOT_ENGAGED = "not_engaged"
    """No manual override is engaged: the stream moves nothing."""
    NOT_HOLDER = "not_holder"
    """From a host other than the override holder's."""
    BAD_TAG = "bad_tag"
    """Tag missing or not made with the holder's session key."""
    STALE = "stale"
    """Older than ``velocity.max_age_ms`` on arrival (or from further in the future than that:
    the sender's clock estimate is wrong): a burst after a lag spike moves nothing."""
    HELD = "held"
    """The failsafe ladder holds (the link was lost): nothing moves until the operator
    re-engages, and nothing sent before that may move the robot afterwards."""


@dataclass(frozen=True)
class PvelSentence:
    """A checksum-valid, in-range sentence. ``x_text``/``z_text`` are the values as sent."""

    count: int
    x: float
    z: float
    x_text: str
    z_text: str
    tag: bytes | None = None
    sent_ms: int | None = None
    """When it was sent, in the receiver's monotonic ms (mod :data:`SENT_MODULUS`) as the
    sender estimated it, if given."""


def checksum(body: bytes) -> int:
    """NMEA-0183: XOR of every byte between ``$`` and ``*``."""
    value = 0
    for byte in body:
        value ^= byte
    return value


def format_value(value: float) -> str:
    """A velocity component as sent: 5 decimals, clamped to [-1, 1], never ``-0.00000``."""
    if value != value:  # NaN: the safe value is standstill
        value = 0.0
    text = f"{max(-1.0, min(1.0, value)):.5f}"
    return "0.00000" if text == "-0.00000" else text


def compute_tag(
    key: bytes,
    session_id: str,
    count: int,
    x_text: str,
    z_text: str,
    sent_ms: int | None = None,
) -> bytes:
    """The sentence's authentication tag, bound to the session, the exact values sent and the
    send time (a sentence without one is tagged as before it existed)."""
    parts = [session_id, str(count), x_text, z_text]
    if sent_ms is not None:
        parts.append(str(sent_ms))
    return security.tag(key, b"brasidas-pvel", *parts)[:TAG_BYTES]


def encode(
    count: int,
    x: float,
    z: float,
    *,
    key: bytes | None = None,
    session_id: str = "",
    sent_ms: int | None = None,
) -> bytes:
    """One ``$PVEL`` datagram; tagged when ``key`` is given, stamped when ``sent_ms`` (the
    receiver's monotonic clock in ms, any size: it is sent modulo :data:`SENT_MODULUS`) is.
    Values are clamped to [-1, 1]."""
    if not 0 <= count <= MAX_COUNT:
        raise ValueError(f"count {count} outside 0..{MAX_COUNT}")
    if sent_ms is not None:
        sent_ms %= SENT_MODULUS
    x_text, z_text = format_value(x), format_value(z)
    body = f"{TALKER},{count},{x_text},{z_text}"
    if sent_ms is not None:
        body += f",{sent_ms}"
    if key is not None:
        body += "," + compute_tag(key, session_id, count, x_text, z_text, sent_ms).hex().upper()
    raw = body.encode("ascii")
    return b"$" + raw + b"*" + f"{checksum(raw):02X}".encode("ascii")


def decode(datagram: bytes) -> PvelSentence | DropReason:
    """Parse one datagram: a sentence, or why it was dropped. Never raises.

    The tag, when present, is returned unchecked: only the receiver knows which session's key
    it must verify against (:func:`verify_tag`).
    """
    if len(datagram) > MAX_DATAGRAM:
        return DropReason.MALFORMED
    data = datagram.rstrip(b"\r\n")
    if len(data) < 4 or data[:1] != b"$" or data[-3:-2] != b"*":
        return DropReason.MALFORMED
    body, received = data[1:-3], data[-2:]
    if not all(c in _HEX for c in received):
        return DropReason.MALFORMED
    if checksum(body) != int(received, 16):
        return DropReason.BAD_CHECKSUM
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError:
        return DropReason.MALFORMED
    match = _BODY.fullmatch(text)
    if match is None:
        return DropReason.MALFORMED
    count = int(match["count"])
    x, z = float(match["x"]), float(match["z"])
    if count > MAX_COUNT or not (-1.0 <= x <= 1.0 and -1.0 <= z <= 1.0):
        return DropReason.OUT_OF_RANGE
    tag = bytes.fromhex(match["tag"]) if match["tag"] else None
    sent = int(match["sent"]) if match["sent"] else None
    return PvelSentence(count, x, z, match["x"], match["z"], tag, sent)


def age_ms(sentence: PvelSentence, now_ms: float) -> float | None:
    """The sentence's age (ms) at ``now_ms`` of the receiver's monotonic clock, None when it
    carries no send time. Negative when the sender's clock estimate runs ahead of ours; the
    wrap of ``sent`` is undone (ages within ±13.9 hours are unambiguous)."""
    if sentence.sent_ms is None:
        return None
    half = SENT_MODULUS // 2
    return (now_ms - sentence.sent_ms + half) % SENT_MODULUS - half


def verify_tag(sentence: PvelSentence, key: bytes, session_id: str) -> bool:
    """Whether ``sentence`` carries a tag made with ``key`` for ``session_id``."""
    if sentence.tag is None:
        return False
    expected = compute_tag(
        key, session_id, sentence.count, sentence.x_text, sentence.z_text, sentence.sent_ms
    )
    return security.verify(expected, sentence.tag)


class PvelEncoder:
    """A sender's sentence factory: auto-incrementing count, tagged for its session, stamped
    with the send time when the caller knows the receiver's clock."""

    def __init__(self, *, key: bytes | None = None, session_id: str = "", start: int = 1) -> None:
        self.key = key
        self.session_id = session_id
        self.next_count = start

    def encode(self, x: float, z: float, sent_ms: int | None = None) -> bytes:
        datagram = encode(
            self.next_count, x, z, key=self.key, session_id=self.session_id, sent_ms=sent_ms
        )
        self.next_count += 1
        return datagram
