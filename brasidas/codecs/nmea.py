"""NMEA-0183 from a GPS receiver, sans-IO: bytes -> sentences -> one fix per epoch.

:class:`NmeaDecoder` frames the serial byte stream into checked sentences parsed with
pynmea2; binary noise, bad checksums, truncated and unknown sentences are dropped and counted
(:class:`DropReason`). :class:`EpochAssembler` groups sentences by their UTC time into epochs
and yields one :class:`~brasidas.messages.GpsFix` per epoch with a fix.

When an epoch is complete: a receiver sends its epoch as one burst in a fixed order (u-blox:
RMC VTG GGA GSA GSV.. GLL [ZDA]; SiRF: GGA [GSA GSV..] RMC VTG). The last sentence type before
the time changes is learned as the *cycle ender* (as gpsd does), and later epochs are
published as soon as their ender arrives, not a second later. An epoch cut short by a new
time before its ender (the receiver restarted or was reconfigured mid-burst) is dropped as
incomplete; one left hanging by a silent line is published after ``quiet`` seconds.
"""

from __future__ import annotations

import dataclasses
import re
from collections import Counter
from datetime import date, datetime, time
from enum import StrEnum

import pynmea2

from brasidas.messages import GpsFix

MAX_SENTENCE = 120
"""Longest sentence accepted (NMEA says 82; u-blox TXT and some SiRF lines run longer)."""
MAX_PENDING = 512
"""Bytes kept without a line end before the buffer is treated as noise."""
KNOTS_TO_MPS = 1852.0 / 3600.0
HANDLED = frozenset({"RMC", "GGA", "GSA", "VTG", "GLL", "ZDA"})
"""Sentence types that feed fixes; other known types (GSV, TXT...) are counted and ignored."""
TIMED = frozenset({"RMC", "GGA", "GLL", "ZDA"})
EARLY = frozenset({"RMC", "GGA"})
"""An epoch whose cycle carries these is published once both arrived, before its ender."""

_SENTENCE = re.compile(rb"^\$([A-Z0-9]{3,6}),([\x20-\x7e]*)\*([0-9A-Fa-f]{2})$")


class DropReason(StrEnum):
    CHECKSUM = "checksum"
    MALFORMED = "malformed"
    """Truncated (no ``*hh``), too long, cut by another ``$``, or fields pynmea2 rejects."""
    UNKNOWN = "unknown"
    """A well-formed sentence of a type pynmea2 does not know (e.g. proprietary)."""
    NOISE = "noise"
    """Binary noise or text outside any sentence (one count per run)."""


def checksum(body: str) -> int:
    """XOR of the characters between ``$`` and ``*``."""
    value = 0
    for byte in body.encode("ascii"):
        value ^= byte
    return value


def sentence(body: str) -> bytes:
    """A complete sentence on the wire: ``$body*hh\\r\\n``."""
    return f"${body}*{checksum(body):02X}\r\n".encode("ascii")


class NmeaDecoder:
    """Serial bytes in, parsed pynmea2 sentences out; everything else dropped and counted."""

    def __init__(self) -> None:
        self._pending = bytearray()
        self.sentences = 0
        """Sentences with a valid checksum, of any type."""
        self.by_type: Counter[str] = Counter()
        self.dropped: dict[str, int] = {reason.value: 0 for reason in DropReason}

    def feed(self, data: bytes) -> list[pynmea2.NMEASentence]:
        """Parse every complete line in ``data`` (plus what was pending)."""
        self._pending += data
        out: list[pynmea2.NMEASentence] = []
        while True:
            end = self._pending.find(b"\n")
            if end < 0:
                break
            line = bytes(self._pending[:end])
            del self._pending[: end + 1]
            self._line(line.rstrip(b"\r"), out)
        if len(self._pending) > MAX_PENDING:
            # No line end in sight: binary noise. Keep a sentence that may be starting.
            start = self._pending.rfind(b"$")
            if start < 0 or len(self._pending) - start > MAX_SENTENCE:
                start = len(self._pending)
            del self._pending[:start]
            self._drop(DropReason.NOISE)
        return out

    def reset(self) -> None:
        """Forget a partial line (the port was reopened)."""
        self._pending.clear()

    def _drop(self, reason: DropReason) -> None:
        self.dropped[reason.value] += 1

    def _line(self, line: bytes, out: list[pynmea2.NMEASentence]) -> None:
        if not line.strip():
            return
        parts = line.split(b"$")
        if parts[0]:
            # Text before the first '$': binary noise (as in front of a u-blox burst).
            self._drop(DropReason.NOISE)
        for part in parts[1:-1]:
            if part:  # a sentence cut short by the next '$'
                self._drop(DropReason.MALFORMED)
        if len(parts) > 1:
            self._sentence(b"$" + parts[-1], out)

    def _sentence(self, raw: bytes, out: list[pynmea2.NMEASentence]) -> None:
        if len(raw) > MAX_SENTENCE:
            self._drop(DropReason.MALFORMED)
            return
        match = _SENTENCE.match(raw)
        if match is None:
            if any(byte > 0x7E or (byte < 0x20 and byte != 0x09) for byte in raw):
                self._drop(DropReason.NOISE)
            else:
                self._drop(DropReason.MALFORMED)
            return
        text = raw.decode("ascii")
        body = text[1:-3]
        if checksum(body) != int(text[-2:], 16):
            self._drop(DropReason.CHECKSUM)
            return
        address = match.group(1).decode("ascii")
        kind = address[2:] if len(address) == 5 and not address.startswith("P") else address
        if kind not in pynmea2.TalkerSentence.sentence_types:
            self._drop(DropReason.UNKNOWN)
            return
        self.sentences += 1
        self.by_type[kind] += 1
        if kind not in HANDLED:
            return
        try:
            parsed = pynmea2.parse(text, check=False)
            # pynmea2 hands back the raw string when a time does not parse: not a sentence
            # to build an epoch on.
            if kind in TIMED and isinstance(parsed.timestamp, str) and parsed.timestamp:
                raise ValueError(f"bad time {parsed.timestamp!r}")
        except (pynmea2.ParseError, ValueError, TypeError):
            self._drop(DropReason.MALFORMED)
            self.sentences -= 1
            self.by_type[kind] -= 1
            return
        out.append(parsed)


@dataclasses.dataclass
class _Epoch:
    utc: time | None
    last_type: str = ""
    published: bool = False
    types: set[str] = dataclasses.field(default_factory=set)
    latitude: float | None = None
    longitude: float | None = None
    altitude_m: float | None = None
    speed_mps: float | None = None
    course_deg: float | None = None
    quality: int | None = None
    satellites: int | None = None
    hdop: float | None = None
    fix_asserted: bool = False
    fix_denied: bool = False


class EpochAssembler:
    """Parsed sentences in, at most one :class:`GpsFix` per epoch out (see module doc)."""

    def __init__(self, quiet: float = 0.3) -> None:
        self.quiet = quiet
        self.ender: str | None = None
        """The learned cycle-ending sentence type."""
        self.epochs = 0
        self.incomplete = 0
        """Epochs dropped because a new time began before their cycle ender."""
        self.no_fix = 0
        """Epochs in which the receiver said it had no fix."""
        self._epoch: _Epoch | None = None
        self._orphans: list[pynmea2.NMEASentence] = []
        self._candidate: str | None = None
        self.cycle: frozenset[str] = frozenset()
        """Sentence types of the last complete cycle (ended by the ender)."""
        self._date: date | None = None
        self._last_input = 0.0

    @property
    def pending(self) -> bool:
        """An epoch is waiting for its ender (publish it at :meth:`deadline` if the line stays quiet)."""
        return self._epoch is not None and not self._epoch.published

    def deadline(self) -> float | None:
        """When :meth:`poll` will flush a pending epoch (the caller's clock), or None."""
        return self._last_input + self.quiet if self.pending else None

    def feed(self, msg: pynmea2.NMEASentence, now: float) -> list[GpsFix | None]:
        """One sentence; returns fixes published (None: an epoch completed without a fix)."""
        self._last_input = now
        out: list[GpsFix | None] = []
        kind = msg.sentence_type
        if kind in TIMED:
            # A receiver without a fix may not know the time either ($GPRMC,,V,...): those
            # sentences form a time-less epoch of their own.
            utc = getattr(msg, "timestamp", None)
            utc = utc.replace(tzinfo=None) if isinstance(utc, time) else None
            if self._epoch is None or self._epoch.utc != utc:
                self._close(out)
                self._epoch = _Epoch(utc)
        epoch = self._epoch
        if epoch is None:
            return out  # untimed sentences before the first timed one: no epoch to join
        epoch.types.add(kind)
        epoch.last_type = kind
        if not epoch.published:
            self._merge(epoch, msg)
            if kind == self.ender or self._early(epoch):
                out.append(self._publish(epoch))
        return out

    def touch(self, now: float) -> None:
        """Bytes arrived (of any sentence, GSV included): the line is not quiet."""
        self._last_input = now

    def _early(self, epoch: _Epoch) -> bool:
        """The epoch already holds every fix sentence its cycle brings (RMC and GGA)."""
        need = self.cycle & EARLY
        return bool(need) and need <= epoch.types and epoch.fix_asserted and not epoch.fix_denied

    def poll(self, now: float) -> list[GpsFix | None]:
        """Publish an epoch left pending by a line quiet since ``quiet`` seconds."""
        epoch = self._epoch
        if epoch is None or epoch.published or now - self._last_input < self.quiet:
            return []
        if self.ender is None:  # the burst is over: its last sentence ends the cycle
            self.ender = epoch.last_type
        return [self._publish(epoch)]

    def _close(self, out: list[GpsFix | None]) -> None:
        epoch = self._epoch
        if epoch is None:
            return
        if epoch.last_type == self.ender:
            self.cycle = frozenset(epoch.types)
        if epoch.published:
            return
        if self.ender is None:
            # Still learning: the first complete epoch tells where the cycle ends.
            self.ender = epoch.last_type
            self.cycle = frozenset(epoch.types)
            out.append(self._publish(epoch))
            return
        self.incomplete += 1
        # The receiver's output may have changed: adopt a new ender seen twice in a row.
        if self._candidate == epoch.last_type:
            self.ender = epoch.last_type
            self._candidate = None
        else:
            self._candidate = epoch.last_type

    def _publish(self, epoch: _Epoch) -> GpsFix | None:
        epoch.published = True
        self.epochs += 1
        if self._candidate is not None and epoch.last_type == self.ender:
            self._candidate = None
        fix = epoch.fix_asserted and not epoch.fix_denied
        if not fix or epoch.latitude is None or epoch.longitude is None:
            self.no_fix += 1
            return None
        if epoch.utc is None:  # a position without a time: not a fix anyone can use
            self.no_fix += 1
            return None
        when = epoch.utc.isoformat(timespec="milliseconds")
        if self._date is not None:
            when = f"{self._date.isoformat()}T{when}"
        return GpsFix(
            latitude=epoch.latitude,
            longitude=epoch.longitude,
            altitude_m=epoch.altitude_m,
            speed_mps=epoch.speed_mps,
            course_deg=epoch.course_deg,
            quality=epoch.quality if epoch.quality is not None else 1,
            satellites=epoch.satellites,
            hdop=epoch.hdop,
            time=when + "Z",
        )

    def _merge(self, epoch: _Epoch, msg: pynmea2.NMEASentence) -> None:
        kind = msg.sentence_type
        if kind == "GGA":
            quality = _int(msg.gps_qual)
            satellites = _int(msg.num_sats)
            epoch.quality = quality
            epoch.satellites = satellites
            epoch.hdop = _float(msg.horizontal_dil)
            epoch.altitude_m = _float(msg.altitude)
            if not quality or satellites == 0:
                # A SiRF reports quality 1 with no satellites while it acquires: not a fix.
                epoch.fix_denied = True
            else:
                epoch.fix_asserted = True
                self._position(epoch, msg)
        elif kind == "RMC":
            if msg.status == "A" and msg.mode_indicator != "N":
                epoch.fix_asserted = True
                self._position(epoch, msg)
            else:
                epoch.fix_denied = True
            knots = _float(msg.spd_over_grnd)
            if knots is not None:
                epoch.speed_mps = knots * KNOTS_TO_MPS
            course = _float(msg.true_course)
            if course is not None:
                epoch.course_deg = course
            if isinstance(msg.datestamp, date):
                self._date = msg.datestamp
        elif kind == "GLL":
            if msg.status == "A":
                epoch.fix_asserted = True
                self._position(epoch, msg)
            else:
                epoch.fix_denied = True
        elif kind == "VTG":
            kmph = _float(msg.spd_over_grnd_kmph)
            if kmph is not None and epoch.speed_mps is None:
                epoch.speed_mps = kmph / 3.6
            course = _float(msg.true_track)
            if course is not None and epoch.course_deg is None:
                epoch.course_deg = course
        elif kind == "GSA":
            if _int(msg.mode_fix_type) == 1:
                epoch.fix_denied = True
            hdop = _float(msg.hdop)
            if hdop is not None and epoch.hdop is None:
                epoch.hdop = hdop
        elif kind == "ZDA":
            try:
                self._date = date(int(msg.year), int(msg.month), int(msg.day))
            except (TypeError, ValueError):
                pass

    @staticmethod
    def _position(epoch: _Epoch, msg: pynmea2.NMEASentence) -> None:
        if not msg.lat or not msg.lon:
            return
        try:
            latitude, longitude = float(msg.latitude), float(msg.longitude)
        except (TypeError, ValueError):
            return
        if -90.0 <= latitude <= 90.0 and -180.0 <= longitude <= 180.0:
            epoch.latitude, epoch.longitude = latitude, longitude


def utc_of(fix: GpsFix) -> datetime | None:
    """The fix's UTC time as a datetime when it carries a date."""
    try:
        return datetime.fromisoformat(fix.time.replace("Z", "+00:00"))
    except ValueError:
        return None


def _int(value: object) -> int | None:
    try:
        return int(str(value))
    except (TypeError, ValueError):
        return None


def _float(value: object) -> float | None:
    if value is None or value == "":
        return None
    try:
        return float(str(value))
    except (TypeError, ValueError):
        return None
