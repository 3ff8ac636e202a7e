"""MAVLink 2 message signing (mavlink.io "message signing"), sans-IO.

The key is SHA-256 of a passphrase read from ``mavlink.signing_key_file`` (MAVProxy's
``signing setup PASS`` and QGroundControl derive it the same way). Incoming frames are checked
here rather than by pymavlink's parser, which records a stream's timestamp *before* it checks
the signature: one forged frame with a far-future timestamp would then lock the real ground
station out. Here a timestamp counts only once its signature verifies.

Replay state is the vehicle's, not a UDP address's (mavlink.io's rule): one table of streams
(link id, system, component) with each one's newest timestamp, shared by every link, so a
captured session sent again from a new source port is a replay. A stream not in the table is
accepted only if its timestamp is within a minute of the vehicle's :class:`SigningClock`, which
follows the wall clock, GPS time and good signed frames, never goes back, and is saved with
the table across restarts (:func:`save_state`, as ArduPilot keeps its signing timestamp).
"""

from __future__ import annotations

import enum
import hashlib
import hmac
import json
from collections.abc import Callable
from pathlib import Path

from brasidas.autonomy.route import write_atomically
from brasidas.files import FileReadError, read_regular_file
from brasidas.security import PrivateFileError, read_private_file

SIGNED_FLAG = 0x01
"""MAVLINK_IFLAG_SIGNED: the incompat flag of a signed frame."""
SIGNATURE_LENGTH = 13
"""Link id (1), timestamp (6), signature (6)."""
EPOCH_UNIX = 1_420_070_400
"""2015-01-01T00:00:00Z: the signing timestamp's epoch."""
NEW_STREAM_SLACK = 60 * 100_000
"""A new stream may start up to a minute behind the vehicle's signing clock (10 µs units)."""
SAVE_INTERVAL_S = 5.0
"""The signing state is saved this often while it changes (and when the endpoint stops)."""
UNCLEAN_STOP_SLACK = int(SAVE_INTERVAL_S * 100_000) + 1
"""After a stop that did not save (a crash, a power cut), every stream's last timestamp is
taken as this much later than saved: frames newer than the last save are refused too (a
ground station still talking resumes at most this much later)."""
STATE_MAX_BYTES = 64 * 1024
MAX_STREAMS = 64
"""Streams remembered; a flood of made-up stream ids cannot grow the table without bound."""


class SigningKeyError(PrivateFileError):
    """The passphrase file is missing, unreadable, not a regular file, too large, accessible by
    others, or not one line of text."""


def load_signing_key(path: Path) -> bytes:
    """SHA-256 of the file's one line (trailing newline ignored). The file is a secret under
    the fleet key's rules (:func:`brasidas.security.read_private_file`: a regular file of
    bounded size, this user's, no group or other bits). Blocking: call it at start."""
    try:
        data = read_private_file(path, "MAVLink signing key")
    except PrivateFileError as err:
        raise SigningKeyError(str(err)) from None
    try:
        text = data.decode("utf-8")
    except UnicodeDecodeError:
        raise SigningKeyError(f"{path}: the MAVLink signing key is not UTF-8 text") from None
    passphrase = text.removesuffix("\n").removesuffix("\r")
    if not passphrase or "\n" in passphrase:
        raise SigningKeyError(f"{path}: expected one non-empty line")
    return key_from_passphrase(passphrase)


def key_from_passphrase(passphrase: str) -> bytes:
    return hashlib.sha256(passphrase.encode()).digest()


def timestamp_at(unix_time: float) -> int:
    """The signing timestamp (10 µs units since 2015-01-01) of a wall-clock time."""
    return max(0, int((unix_time - EPOCH_UNIX) * 100_000))


class Verdict(enum.Enum):
    SIGNED = "signed"
    """Signature and timestamp good."""
    UNSIGNED = "unsigned"
    BAD_SIGNATURE = "bad_signature"
    REPLAY = "replay"
    """A timestamp not newer than the stream's last one (or a new stream a minute behind)."""


class SigningClock:
    """The vehicle's signing time (10 µs units since 2015): the newest of the wall clock, GPS
    time, good signed timestamps and what was saved before a restart. It never goes back, so a
    robot that boots with its clock at 1970 (no RTC) still refuses an old capture."""

    def __init__(self, wall: Callable[[], float] | None = None, timestamp: int = 0) -> None:
        self.wall = wall
        self.timestamp = timestamp

    def advance(self, timestamp: int) -> None:
        self.timestamp = max(self.timestamp, timestamp)

    def now(self) -> int:
        if self.wall is not None:
            self.advance(timestamp_at(self.wall()))
        return self.timestamp


Stream = tuple[int, int, int]
"""(link id, system id, component id) of a signed frame's sender."""


class SignatureCheck:
    """Checks signed frames against the key with one replay table for the whole vehicle;
    counts every verdict."""

    def __init__(self, key: bytes, clock: SigningClock | None = None) -> None:
        self.key = key
        self.clock = clock if clock is not None else SigningClock()
        self.streams: dict[Stream, int] = {}
        self.counters: dict[Verdict, int] = dict.fromkeys(Verdict, 0)
        self.changed = False
        """A stream or the clock moved since the last :meth:`state`."""

    def state(self) -> dict[str, object]:
        """What :func:`save_state` writes; clears :attr:`changed`."""
        self.changed = False
        return {
            "timestamp": self.clock.now(),
            "streams": [[*stream, last] for stream, last in self.streams.items()],
        }

    def restore(self, state: SavedState) -> None:
        """Take the saved clock and streams (after a stop that did not save, a little later)."""
        slack = 0 if state.clean else UNCLEAN_STOP_SLACK
        self.clock.advance(state.timestamp + slack)
        for stream, last in state.streams.items():
            self.streams[stream] = max(self.streams.get(stream, 0), last + slack)

    def check(self, frame: bytes | bytearray) -> Verdict:
        """The verdict on one whole MAVLink 2 frame (header to signature)."""
        verdict = self._check(frame)
        self.counters[verdict] += 1
        return verdict

    def _check(self, frame: bytes | bytearray) -> Verdict:
        if len(frame) < 12 + SIGNATURE_LENGTH or frame[0] != 0xFD:
            return Verdict.UNSIGNED
        if not frame[2] & SIGNED_FLAG:
            return Verdict.UNSIGNED
        link_id = frame[-13]
        timestamp = int.from_bytes(frame[-12:-6], "little")
        digest = hashlib.sha256(self.key + bytes(frame[:-6])).digest()[:6]
        if not hmac.compare_digest(digest, bytes(frame[-6:])):
            return Verdict.BAD_SIGNATURE
        stream = (link_id, frame[5], frame[6])
        last = self.streams.get(stream)
        if last is not None and timestamp <= last:
            return Verdict.REPLAY
        if last is None and timestamp + NEW_STREAM_SLACK < self.clock.now():
            return Verdict.REPLAY
        if last is None and len(self.streams) >= MAX_STREAMS:
            # The stream heard from longest ago goes: its old frames are then a minute behind.
            del self.streams[min(self.streams, key=self.streams.__getitem__)]
        self.streams[stream] = timestamp
        self.clock.advance(timestamp)
        self.changed = True
        return Verdict.SIGNED


class SavedState:
    """The signing clock and replay table as saved (:func:`load_state`)."""

    def __init__(self, timestamp: int, streams: dict[Stream, int], clean: bool) -> None:
        self.timestamp = timestamp
        self.streams = streams
        self.clean = clean


def save_state(path: Path, state: dict[str, object], *, clean: bool) -> None:
    """Write the signing state (``clean``: the endpoint is stopping, nothing comes after).
    Blocking: call it in a thread."""
    write_atomically(path, json.dumps({**state, "clean": clean}))


def load_state(path: Path) -> SavedState | None:
    """The saved signing state; None when there is none. A file that is not one (damaged,
    edited) raises :class:`ValueError`: starting with no replay state would accept a replay.
    Blocking: call it in a thread."""
    if not path.exists() and not path.is_symlink():
        return None
    try:
        data = read_regular_file(path, "MAVLink signing state", STATE_MAX_BYTES)
    except FileReadError as err:
        raise ValueError(str(err)) from None
    try:
        plain = json.loads(data)
        timestamp = plain["timestamp"]
        streams: dict[Stream, int] = {}
        for link_id, system, component, last in plain["streams"][:MAX_STREAMS]:
            values = (link_id, system, component, last)
            if not all(type(v) is int and v >= 0 for v in values):
                raise ValueError("a stream is not four counts")
            streams[(link_id, system, component)] = last
        if type(timestamp) is not int or timestamp < 0:
            raise ValueError("the timestamp is not a count")
        return SavedState(timestamp, streams, plain.get("clean") is True)
    except (ValueError, KeyError, TypeError) as err:
        raise ValueError(f"{path}: not a MAVLink signing state ({err})") from None
