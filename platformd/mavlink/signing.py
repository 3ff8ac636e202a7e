"""MAVLink 2 message signing (mavlink.io "message signing"), sans-IO.

The key is SHA-256 of a passphrase read from ``mavlink.signing_key_file`` (MAVProxy's
``signing setup PASS`` and QGroundControl derive it the same way). Incoming frames are checked
here rather than by pymavlink's parser, which records a stream's timestamp *before* it checks
the signature: one forged frame with a far-future timestamp would then lock the real ground
station out. Here a timestamp counts only once its signature verifies.
"""

from __future__ import annotations

import enum
import hashlib
import hmac
from pathlib import Path

from brasidas.security import PrivateFileError, read_private_file

SIGNED_FLAG = 0x01
"""MAVLINK_IFLAG_SIGNED: the incompat flag of a signed frame."""
SIGNATURE_LENGTH = 13
"""Link id (1), timestamp (6), signature (6)."""
EPOCH_UNIX = 1_420_070_400
"""2015-01-01T00:00:00Z: the signing timestamp's epoch."""
NEW_STREAM_SLACK = 60 * 100_000
"""A new stream may start up to a minute behind the newest timestamp seen (10 µs units)."""
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


class SignatureCheck:
    """Checks signed frames of one link against the key; counts every verdict."""

    def __init__(self, key: bytes) -> None:
        self.key = key
        self.newest = 0
        """The newest good timestamp seen on this link."""
        self.streams: dict[tuple[int, int, int], int] = {}
        self.counters: dict[Verdict, int] = dict.fromkeys(Verdict, 0)

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
        if last is None and timestamp + NEW_STREAM_SLACK < self.newest:
            return Verdict.REPLAY
        if last is None and len(self.streams) >= MAX_STREAMS:
            self.streams.pop(next(iter(self.streams)))
        self.streams[stream] = timestamp
        self.newest = max(self.newest, timestamp)
        return Verdict.SIGNED
