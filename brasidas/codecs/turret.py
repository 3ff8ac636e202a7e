"""The turret line protocol (issue 13): a microcontroller with azimuth/elevation servos and a
trigger, on a serial line. Sans-IO: :func:`encode` and :class:`LineDecoder`.

Every line is ``$<body>*<XX>\\n``, ``XX`` the XOR of the body's bytes in hex (as NMEA).
Driver → microcontroller, each with a sequence number 0-255 the answer repeats::

    $C,<seq>,AIM,<az_deg>,<el_deg>*XX   move the servos (az -180..180, el -10..60)
    $C,<seq>,FIRE*XX                    press the trigger
    $C,<seq>,SAFE*XX                    release the trigger, servos hold where they are
    $C,<seq>,PING*XX                    keep-alive (any valid command feeds the watchdog)

Microcontroller → driver::

    $A,<seq>,OK,<az>,<el>,<trigger 0|1>*XX     done; the state after it
    $A,<seq>,ERR,<reason>*XX                   refused (out of range, unknown)
    $W,<az>,<el>*XX                            the watchdog released the trigger

A line with a bad checksum is dropped and counted by whoever reads it: the driver resends a
command whose acknowledgement does not come (same sequence number: the microcontroller answers
a repeat without acting twice). The microcontroller releases the trigger by itself when no valid
command arrived for its watchdog time (the driver pings at a third of it).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

MAX_LINE = 80
AZIMUTH_RANGE = (-180.0, 180.0)
ELEVATION_RANGE = (-10.0, 60.0)


class Drop(Enum):
    """Why a received line was not a message."""

    MALFORMED = "malformed"
    BAD_CHECKSUM = "bad_checksum"
    TOO_LONG = "too_long"


@dataclass(frozen=True)
class Line:
    """One valid line: its kind (``C``, ``A``, ``W``) and comma-separated fields."""

    kind: str
    fields: tuple[str, ...]


def checksum(body: bytes) -> int:
    value = 0
    for byte in body:
        value ^= byte
    return value


def encode(kind: str, *fields: object) -> bytes:
    """``$kind,f1,f2*XX\\n``."""
    body = ",".join([kind, *(str(field) for field in fields)]).encode("ascii")
    return b"$" + body + f"*{checksum(body):02X}\n".encode("ascii")


def command(seq: int, name: str, *args: float) -> bytes:
    """A driver command line (``AIM`` arguments to one decimal)."""
    return encode("C", seq, name, *(f"{arg:.1f}" for arg in args))


class LineDecoder:
    """Bytes in, valid lines and drop reasons out."""

    def __init__(self) -> None:
        self._buffer = bytearray()
        self.dropped: dict[Drop, int] = dict.fromkeys(Drop, 0)

    def feed(self, data: bytes) -> list[Line | Drop]:
        out: list[Line | Drop] = []
        self._buffer += data
        while (end := self._buffer.find(b"\n")) >= 0:
            raw = bytes(self._buffer[:end]).strip(b"\r")
            del self._buffer[: end + 1]
            out.append(self._decode(raw))
        if len(self._buffer) > MAX_LINE:
            self._buffer.clear()
            out.append(Drop.TOO_LONG)
        for item in out:
            if isinstance(item, Drop):
                self.dropped[item] += 1
        return out

    @staticmethod
    def _decode(raw: bytes) -> Line | Drop:
        start = raw.rfind(b"$")
        star = raw.rfind(b"*")
        if start < 0 or star < start or len(raw) - star != 3:
            return Drop.MALFORMED
        body = raw[start + 1 : star]
        try:
            if int(raw[star + 1 :], 16) != checksum(body):
                return Drop.BAD_CHECKSUM
            parts = body.decode("ascii").split(",")
        except (ValueError, UnicodeDecodeError):
            return Drop.MALFORMED
        if not parts[0]:
            return Drop.MALFORMED
        return Line(parts[0], tuple(parts[1:]))
