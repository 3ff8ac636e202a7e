"""LDROBOT LD06 / LD19 / STL-27L lidar frames: sans-IO decoder, scan assembler and encoder.

Written from the published frame specification (the vendor's development manual; ArduPilot
reads the same frame). The sensor streams one-way, 8N1 (LD06/LD19 230400 baud, STL-27L
921600), frames of 47 bytes, little-endian:

====== ===== ===========================================================================
offset bytes field
====== ===== ===========================================================================
0      1     header ``0x54``
1      1     ``VerLen``: ``0x2C`` (packet type 1, 12 points per frame)
2      2     rotation speed, degrees per second
4      2     start angle, 0.01 degree
6      36    12 x (distance u16 mm, intensity u8)
42     2     end angle, 0.01 degree
44     2     timestamp, ms (wraps at 30000 on the LD19)
46     1     CRC-8 (polynomial 0x4D, initial value 0, not reflected) of bytes 0-45
====== ===== ===========================================================================

Angles grow clockwise seen from above (the sensor's convention; the reader turns them into the
robot's counter-clockwise frame). The points of a frame are spread evenly from the start to the
end angle, which may wrap through 360 degrees. A distance of 0 is no return. Bytes that do
not make a valid frame are skipped and counted: ``resync_bytes`` (bytes thrown away looking for
a header) and ``crc_errors`` (a header followed by 45 bytes that fail the CRC).
"""

from __future__ import annotations

import functools
import struct
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

HEADER = 0x54
VER_LEN = 0x2C
POINTS_PER_FRAME = 12
FRAME_BYTES = 47
CRC_POLY = 0x4D
_HEADER_BYTES = bytes((HEADER, VER_LEN))
_BODY = struct.Struct("<BBHH" + "HB" * POINTS_PER_FRAME + "HH")


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ CRC_POLY) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        table.append(crc)
    return tuple(table)


CRC_TABLE = _crc_table()


def crc8(data: bytes | bytearray | memoryview) -> int:
    """CRC-8, polynomial 0x4D, initial value 0, no reflection, no final XOR."""
    crc = 0
    for byte in data:
        crc = CRC_TABLE[crc ^ byte]
    return crc


@dataclass(frozen=True)
class LidarFrame:
    """One decoded frame: 12 points from ``start_deg`` to ``end_deg`` (clockwise)."""

    speed_dps: int
    """Rotation speed, degrees per second (3600 = 10 Hz)."""
    start_deg: float
    end_deg: float
    distances_mm: tuple[int, ...]
    """0 = no return."""
    intensities: tuple[int, ...]
    timestamp_ms: int
    received: float
    """When the decoder had its last byte (the caller's clock)."""

    def angles_deg(self) -> list[float]:
        """Each point's angle in [0, 360): evenly spread, wrapping through 360."""
        span = (self.end_deg - self.start_deg) % 360.0
        step = span / (POINTS_PER_FRAME - 1)
        return [(self.start_deg + step * i) % 360.0 for i in range(POINTS_PER_FRAME)]


def encode_frame(
    speed_dps: int,
    start_deg: float,
    end_deg: float,
    distances_mm: Sequence[int],
    intensities: Sequence[int],
    timestamp_ms: int,
) -> bytes:
    """A frame as the sensor sends it (for the simulator and tests)."""
    if len(distances_mm) != POINTS_PER_FRAME or len(intensities) != POINTS_PER_FRAME:
        raise ValueError(f"a frame has {POINTS_PER_FRAME} points")
    points: list[int] = []
    for distance, intensity in zip(distances_mm, intensities, strict=True):
        points += (max(0, min(0xFFFF, int(distance))), max(0, min(0xFF, int(intensity))))
    body = _BODY.pack(
        HEADER,
        VER_LEN,
        speed_dps & 0xFFFF,
        round(start_deg * 100) % 36000,
        *points,
        round(end_deg * 100) % 36000,
        timestamp_ms % 0x10000,
    )
    return body + bytes((crc8(body),))


def encode_frames(
    speed_dps: int,
    starts_deg: Any,
    ends_deg: Any,
    distances_mm: Any,
    intensities: Any,
    timestamps_ms: Any,
) -> bytes:
    """Many frames back to back, each as :func:`encode_frame` packs it, in one NumPy pass (the
    simulator sends hundreds a second): ``starts_deg``, ``ends_deg``, ``timestamps_ms`` one
    value a frame, ``distances_mm`` and ``intensities`` shaped (frames, 12)."""
    import numpy as np  # here: the reader's import of this codec stays light

    count = len(starts_deg)
    wire = np.zeros(count, dtype=_wire_dtype())
    wire["header"] = HEADER
    wire["ver_len"] = VER_LEN
    wire["speed"] = speed_dps & 0xFFFF
    wire["start"] = np.rint(np.asarray(starts_deg, dtype=float) * 100).astype(np.int64) % 36000
    points = wire["points"]
    points["distance"] = np.clip(np.asarray(distances_mm).astype(np.int64), 0, 0xFFFF)
    points["intensity"] = np.clip(np.asarray(intensities).astype(np.int64), 0, 0xFF)
    wire["end"] = np.rint(np.asarray(ends_deg, dtype=float) * 100).astype(np.int64) % 36000
    wire["timestamp"] = np.asarray(timestamps_ms).astype(np.int64) % 0x10000
    data = wire.view(np.uint8).reshape(count, FRAME_BYTES)
    table = np.array(CRC_TABLE, dtype=np.uint8)
    crc = np.zeros(count, dtype=np.uint8)
    for column in data[:, : FRAME_BYTES - 1].T:
        crc = table[crc ^ column]
    data[:, FRAME_BYTES - 1] = crc
    return bytes(data.tobytes())


@functools.cache
def _wire_dtype() -> Any:
    """A frame's fields as a NumPy record, laid out as :data:`_BODY` plus the CRC."""
    import numpy as np

    return np.dtype(
        [
            ("header", "u1"),
            ("ver_len", "u1"),
            ("speed", "<u2"),
            ("start", "<u2"),
            ("points", [("distance", "<u2"), ("intensity", "u1")], (POINTS_PER_FRAME,)),
            ("end", "<u2"),
            ("timestamp", "<u2"),
            ("crc", "u1"),
        ]
    )


class LidarDecoder:
    """Bytes in, frames out; resynchronizes on the header after garbage or a bad CRC."""

    def __init__(self) -> None:
        self._buffer = bytearray()
        self.frames = 0
        self.crc_errors = 0
        self.resync_bytes = 0

    def reset(self) -> None:
        self._buffer.clear()

    def feed(self, data: bytes, now: float) -> Iterator[LidarFrame]:
        buffer = self._buffer
        buffer += data
        while True:
            start = _find_header(buffer)
            if start < 0:
                # Keep a trailing 0x54: it may be the next frame's first byte.
                keep = 1 if buffer and buffer[-1] == HEADER else 0
                self.resync_bytes += len(buffer) - keep
                del buffer[: len(buffer) - keep]
                return
            if start:
                self.resync_bytes += start
                del buffer[:start]
            if len(buffer) < FRAME_BYTES:
                return
            if crc8(memoryview(buffer)[: FRAME_BYTES - 1]) != buffer[FRAME_BYTES - 1]:
                # Not a frame (or a damaged one): skip this header and look again after it.
                self.crc_errors += 1
                self.resync_bytes += 1
                del buffer[:1]
                continue
            fields = _BODY.unpack_from(buffer)
            del buffer[:FRAME_BYTES]
            self.frames += 1
            points = fields[4 : 4 + 2 * POINTS_PER_FRAME]
            yield LidarFrame(
                speed_dps=fields[2],
                start_deg=fields[3] / 100.0,
                end_deg=fields[-2] / 100.0,
                distances_mm=tuple(points[0::2]),
                intensities=tuple(points[1::2]),
                timestamp_ms=fields[-1],
                received=now,
            )


def _find_header(buffer: bytearray) -> int:
    return buffer.find(_HEADER_BYTES)


@dataclass(frozen=True)
class LidarScan:
    """One revolution: points in the sensor's frame, angles clockwise from its forward axis."""

    angles_deg: tuple[float, ...]
    ranges_m: tuple[float, ...]
    """0.0 = no return."""
    intensities: tuple[int, ...]
    speed_dps: int
    started: float
    """When its first frame arrived (caller's clock)."""
    ended: float
    """When its last frame arrived: the scan is usable from here."""


class ScanAssembler:
    """Frames in, whole revolutions out: a scan ends where the start angle wraps past 0."""

    def __init__(self, max_points: int = 2400) -> None:
        self.max_points = max_points
        """A revolution never has more (STL-27L: 2160 at 10 Hz): more means a lost wrap."""
        self.scans = 0
        self._angles: list[float] = []
        self._ranges: list[float] = []
        self._intensities: list[int] = []
        self._started = 0.0
        self._last_start = -1.0
        self._speed = 0
        self._ended = 0.0

    def feed(self, frame: LidarFrame) -> LidarScan | None:
        scan = None
        wrapped = self._last_start >= 0 and frame.start_deg < self._last_start
        if (wrapped or len(self._angles) >= self.max_points) and self._angles:
            scan = self._finish()
        self._last_start = frame.start_deg
        if not self._angles:
            self._started = frame.received
        self._angles += frame.angles_deg()
        self._ranges += (d / 1000.0 for d in frame.distances_mm)
        self._intensities += frame.intensities
        self._speed = frame.speed_dps
        self._ended = frame.received
        return scan

    def _finish(self) -> LidarScan:
        scan = LidarScan(
            tuple(self._angles),
            tuple(self._ranges),
            tuple(self._intensities),
            self._speed,
            self._started,
            self._ended,
        )
        self.scans += 1
        self._angles, self._ranges, self._intensities = [], [], []
        return scan
