"""Telemetry datagrams (platform → station): sans-IO encoder and decoder.

Wire layout of one datagram (always shorter than :data:`MAX_DATAGRAM` bytes)::

    version (1) | flags (1) | msgpack [platform_id, seq, timestamp, sections] | tag (16, if flagged)

``sections`` is a map of snapshot sections by their wire keys (``{"gps": {...}, "bat": {...}}``,
see :mod:`brasidas.codecs.telemetry_schema`; this codec only needs them JSON-like). A snapshot
too large for one datagram is split by section over several datagrams, each with its own
sequence number, so the receiver simply merges every accepted datagram into its latest
snapshot: no reassembly, and a lost datagram only delays the sections it carried. A section
too large for a datagram on its own is replaced by that section's error (``{"!": "trimmed..."}``).

The tag is HMAC-SHA256 with the session key over everything before it, truncated to 16 bytes
(:func:`brasidas.security.tag`). The decoder accepts only strictly increasing sequence
numbers, so replayed and reordered-late datagrams are refused and counted.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import msgpack

from brasidas import security
from brasidas.codecs.telemetry_schema import ERROR_KEY, SCHEMA_VERSION, TOGETHER

VERSION = SCHEMA_VERSION
"""The first byte: the telemetry schema's version (:mod:`brasidas.codecs.telemetry_schema`)."""
MAX_DATAGRAM = 1200
"""Every datagram is strictly shorter than this (fits any path MTU on the mesh)."""
TAG_LENGTH = 16
FLAG_AUTHENTICATED = 0x01
TAG_DOMAIN = b"brasidas-telemetry"
HEADER_LENGTH = 2
MAX_DEPTH = 8
"""Nesting limit for section values (decoder guard against hostile payloads)."""

REJECT_REASONS = (
    "truncated",
    "version",
    "unauthenticated",
    "forged",
    "garbage",
    "wrong_platform",
    "replayed",
)
"""Why a datagram can be refused; every reason has a counter in :class:`TelemetryDecoder`."""


class TelemetryDecodeError(ValueError):
    """A datagram refused by the decoder; ``reason`` is one of :data:`REJECT_REASONS`."""

    def __init__(self, reason: str, detail: str = "") -> None:
        super().__init__(f"{reason}: {detail}" if detail else reason)
        self.reason = reason


@dataclass(frozen=True)
class TelemetryFrame:
    """One accepted datagram: a subset of the snapshot's sections."""

    platform_id: str
    seq: int
    timestamp: float
    """The platform's wall clock (seconds since the epoch) when the snapshot was taken."""
    sections: dict[str, Any]
    size: int
    """Bytes on the wire."""


class TelemetryEncoder:
    """Turns snapshots into datagrams; owns the sequence counter of one stream."""

    def __init__(
        self,
        platform_id: str,
        key: bytes | None,
        *,
        max_datagram: int = MAX_DATAGRAM,
        first_seq: int = 1,
    ) -> None:
        self.platform_id = platform_id
        self.key = key
        self.max_datagram = max_datagram
        self.seq = first_seq
        self.trimmed = 0
        """Sections replaced by a placeholder because they could not fit a datagram alone."""
        overhead = HEADER_LENGTH + (TAG_LENGTH if key is not None else 0)
        self._budget = max_datagram - 1 - overhead

    def encode(self, sections: dict[str, Any], timestamp: float) -> list[bytes]:
        """The datagrams carrying ``sections`` (JSON-like values), each < ``max_datagram``."""
        sections = {str(name): clean(value) for name, value in sections.items()}
        packed = self._pack(sections, timestamp, self.seq)
        if len(packed) <= self._budget:
            return [self._seal(packed)]
        sizes = {name: len(_packb({name: value})) for name, value in sections.items()}
        for name in sections:
            if not self._fits({name: sections[name]}):
                self.trimmed += 1
                sections[name] = {ERROR_KEY: f"trimmed: {sizes[name]} bytes do not fit a datagram"}
        units = _units(sections, self._fits)
        groups: list[dict[str, Any]] = []
        # First-fit in decreasing size keeps the datagram count low.
        for unit in sorted(units, key=lambda u: -sum(sizes[n] for n in u)):
            for group in groups:
                if self._fits({**group, **unit}):
                    group.update(unit)
                    break
            else:
                groups.append(dict(unit))
        return [self._seal(self._pack(group, timestamp, self.seq)) for group in groups]

    def _fits(self, sections: dict[str, Any]) -> bool:
        # The largest sequence number msgpack may need keeps the check valid for any seq.
        return len(self._pack(sections, 0.0, 2**64 - 1)) <= self._budget

    def _pack(self, sections: dict[str, Any], timestamp: float, seq: int) -> bytes:
        return _packb([self.platform_id, seq, float(timestamp), sections])

    def _seal(self, packed: bytes) -> bytes:
        flags = FLAG_AUTHENTICATED if self.key is not None else 0
        body = bytes((VERSION, flags)) + packed
        self.seq += 1
        if self.key is None:
            return body
        return body + security.tag(self.key, TAG_DOMAIN, body, length=TAG_LENGTH)


def _units(
    sections: dict[str, Any], fits: Callable[[dict[str, Any]], bool]
) -> list[dict[str, Any]]:
    """The sections in the pieces a split keeps whole: each of :data:`TOGETHER` present
    (when it fits one datagram), every other section alone."""
    units: list[dict[str, Any]] = []
    placed: set[str] = set()
    for names in TOGETHER:
        unit = {name: sections[name] for name in names if name in sections}
        if len(unit) > 1 and fits(unit):
            units.append(unit)
            placed.update(unit)
    units.extend({name: value} for name, value in sections.items() if name not in placed)
    return units


class TelemetryDecoder:
    """Verifies datagrams of one stream (one platform, one session key) and counts refusals."""

    def __init__(self, platform_id: str, key: bytes | None) -> None:
        self.platform_id = platform_id
        self.key = key
        self.last_seq: int | None = None
        self.accepted = 0
        self.rejected: dict[str, int] = dict.fromkeys(REJECT_REASONS, 0)
        self.foreign_version: int | None = None
        """The version byte of the last datagram refused for its version (another schema)."""

    def feed(self, datagram: bytes) -> list[TelemetryFrame]:
        """The accepted frame (a list of one), or ``[]`` when refused (and counted)."""
        try:
            return [self.decode(datagram)]
        except TelemetryDecodeError as err:
            self.rejected[err.reason] += 1
            if err.reason == "version":
                self.foreign_version = datagram[0]
            return []

    def decode(self, datagram: bytes) -> TelemetryFrame:
        """Verify and parse one datagram; raises :class:`TelemetryDecodeError` only."""
        frame = parse(datagram, self.key)
        if frame.platform_id != self.platform_id:
            raise TelemetryDecodeError("wrong_platform", frame.platform_id)
        if self.last_seq is not None and frame.seq <= self.last_seq:
            raise TelemetryDecodeError("replayed", f"seq {frame.seq} <= {self.last_seq}")
        self.last_seq = frame.seq
        self.accepted += 1
        return frame


def parse(datagram: bytes, key: bytes | None) -> TelemetryFrame:
    """Verify the tag (when ``key`` is set) and parse; no sequence check. Stateless."""
    if len(datagram) < HEADER_LENGTH + 1:
        raise TelemetryDecodeError("truncated", f"{len(datagram)} bytes")
    if len(datagram) >= MAX_DATAGRAM:
        raise TelemetryDecodeError("garbage", f"{len(datagram)} bytes is over the limit")
    version, flags = datagram[0], datagram[1]
    if version != VERSION:
        raise TelemetryDecodeError("version", f"version {version}")
    if flags & ~FLAG_AUTHENTICATED:
        raise TelemetryDecodeError("garbage", f"unknown flags {flags:#x}")
    authenticated = bool(flags & FLAG_AUTHENTICATED)
    if key is not None:
        if not authenticated:
            raise TelemetryDecodeError("unauthenticated")
        if len(datagram) < HEADER_LENGTH + 1 + TAG_LENGTH:
            raise TelemetryDecodeError("truncated", f"{len(datagram)} bytes")
        body, received = datagram[:-TAG_LENGTH], datagram[-TAG_LENGTH:]
        expected = security.tag(key, TAG_DOMAIN, body, length=TAG_LENGTH)
        if not security.verify(expected, received):
            raise TelemetryDecodeError("forged", "bad tag")
        packed = body[HEADER_LENGTH:]
    else:
        # Insecure stream: accept either form, ignore a tag we cannot check.
        packed = datagram[HEADER_LENGTH : -TAG_LENGTH if authenticated else None]
    try:
        message = msgpack.unpackb(packed, raw=False, strict_map_key=True, use_list=True)
    except msgpack.ExtraData:
        raise TelemetryDecodeError("garbage", "trailing bytes") from None
    except (ValueError, msgpack.UnpackException) as err:
        reason = "truncated" if isinstance(err, msgpack.OutOfData) else "garbage"
        raise TelemetryDecodeError(reason, type(err).__name__) from None
    except Exception as err:  # the C unpacker raises a few other types on hostile input
        raise TelemetryDecodeError("garbage", type(err).__name__) from None
    if not (isinstance(message, list) and len(message) == 4):
        raise TelemetryDecodeError("garbage", "not a 4-item array")
    platform_id, seq, timestamp, sections = message
    if not isinstance(platform_id, str) or not platform_id:
        raise TelemetryDecodeError("garbage", "platform id")
    if not isinstance(seq, int) or isinstance(seq, bool) or seq < 0:
        raise TelemetryDecodeError("garbage", "sequence number")
    if not isinstance(timestamp, float) or not math.isfinite(timestamp):
        raise TelemetryDecodeError("garbage", "timestamp")
    if not isinstance(sections, dict) or not _plain(sections, 0):
        raise TelemetryDecodeError("garbage", "sections")
    return TelemetryFrame(platform_id, seq, timestamp, sections, len(datagram))


def clean(value: Any, depth: int = 0) -> Any:
    """``value`` made JSON-compatible: tuples become lists, non-finite floats None, keys str."""
    if value is None or isinstance(value, bool | int | str):
        return value
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if depth >= MAX_DEPTH - 1:
        return None
    if isinstance(value, list | tuple):
        return [clean(item, depth + 1) for item in value]
    if isinstance(value, dict):
        return {str(key): clean(item, depth + 1) for key, item in value.items()}
    return str(value)


def _plain(value: Any, depth: int) -> bool:
    """JSON-compatible (so the snapshot can go straight to the local API), finite, shallow."""
    if value is None or isinstance(value, bool | int | str):
        return True
    if isinstance(value, float):
        return math.isfinite(value)
    if depth >= MAX_DEPTH:
        return False
    if isinstance(value, list):
        return all(_plain(item, depth + 1) for item in value)
    if isinstance(value, dict):
        return all(isinstance(key, str) and _plain(item, depth + 1) for key, item in value.items())
    return False


def _packb(value: Any) -> bytes:
    packed: bytes = msgpack.packb(value, use_bin_type=True)
    return packed
