"""The LD06/LD19/STL-27L decoder against frames built from the specification."""

from __future__ import annotations

import itertools
import struct

from brasidas.codecs.ldlidar import (
    FRAME_BYTES,
    POINTS_PER_FRAME,
    LidarDecoder,
    ScanAssembler,
    crc8,
    encode_frame,
    encode_frames,
)


def spec_frame(start: int, end: int, distances: list[int], stamp: int = 1234) -> bytes:
    """A frame laid out by hand from the data sheet's table (not through encode_frame)."""
    body = bytes([0x54, 0x2C]) + struct.pack("<HH", 3600, start)
    for i, distance in enumerate(distances):
        body += struct.pack("<HB", distance, 200 + i)
    body += struct.pack("<HH", end, stamp)
    crc = 0
    for byte in body:  # bitwise CRC-8, poly 0x4D: independent of the decoder's table
        crc ^= byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x4D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
    return body + bytes([crc])


def test_crc8_matches_the_data_sheets_table() -> None:
    # The manual prints the 256-entry table; its first row begins like this.
    assert [crc8(bytes([b])) for b in range(8)] == [0x00, 0x4D, 0x9A, 0xD7, 0x79, 0x34, 0xE3, 0xAE]
    assert crc8(b"") == 0


def test_decodes_a_frame_from_the_specification() -> None:
    distances = [1000 + 10 * i for i in range(12)]
    frame_bytes = spec_frame(1000, 2100, distances, stamp=29999)
    assert len(frame_bytes) == FRAME_BYTES == 47
    decoder = LidarDecoder()
    (frame,) = list(decoder.feed(frame_bytes, now=5.0))
    assert frame.speed_dps == 3600
    assert frame.start_deg == 10.0
    assert frame.end_deg == 21.0
    assert frame.distances_mm == tuple(distances)
    assert frame.intensities == tuple(200 + i for i in range(12))
    assert frame.timestamp_ms == 29999
    assert frame.received == 5.0
    angles = frame.angles_deg()
    assert angles[0] == 10.0
    assert abs(angles[-1] - 21.0) < 1e-9
    assert abs(angles[1] - 11.0) < 1e-9
    assert encode_frame(3600, 10.0, 21.0, distances, list(range(200, 212)), 29999) == frame_bytes


def test_angles_wrap_through_360() -> None:
    (frame,) = list(LidarDecoder().feed(spec_frame(35500, 500, [500] * 12), now=0.0))
    angles = frame.angles_deg()
    assert abs(angles[0] - 355.0) < 1e-9
    assert abs(angles[-1] - 5.0) < 1e-9
    # Evenly spread across the wrap: 10 degrees over 11 steps, never backwards through 180.
    steps = [(b - a) % 360.0 for a, b in itertools.pairwise(angles)]
    assert all(abs(step - 10.0 / 11) < 1e-9 for step in steps)


def test_corrupt_frames_are_counted_and_skipped() -> None:
    good = spec_frame(0, 1100, [700] * 12)
    bad = bytearray(spec_frame(1200, 2300, [800] * 12))
    bad[10] ^= 0x01  # one bit flipped in a distance
    decoder = LidarDecoder()
    frames = list(decoder.feed(b"\x00\x54\xff" + bytes(bad) + good, now=1.0))
    assert [f.start_deg for f in frames] == [0.0]
    assert decoder.crc_errors == 1
    assert decoder.frames == 1
    assert decoder.resync_bytes >= 3 + 1


def test_frames_split_across_reads() -> None:
    stream = b"".join(spec_frame(i * 1200, i * 1200 + 1100, [i + 1] * 12) for i in range(4))
    decoder = LidarDecoder()
    frames = [f for i in range(0, len(stream), 5) for f in decoder.feed(stream[i : i + 5], 0.0)]
    assert [f.distances_mm[0] for f in frames] == [1, 2, 3, 4]
    assert decoder.crc_errors == 0
    assert decoder.resync_bytes == 0


def test_assembler_cuts_a_scan_where_the_angle_wraps() -> None:
    assembler = ScanAssembler()
    decoder = LidarDecoder()
    # 30 frames of 12 degrees: 360 degrees, then the next revolution's first frame.
    stream = b"".join(
        spec_frame((i * 1200) % 36000, (i * 1200 + 1100) % 36000, [1000] * 12) for i in range(31)
    )
    scans = [s for f in decoder.feed(stream, 2.0) if (s := assembler.feed(f)) is not None]
    assert len(scans) == 1
    assert len(scans[0].angles_deg) == 360
    assert scans[0].ranges_m[0] == 1.0


def test_frames_packed_together_are_each_frame_as_encode_frame_packs_it() -> None:
    """The simulator's batch packing and the one-frame packing are one format: the same bytes
    for the same fields, halves rounded and out-of-range values clamped alike."""
    import numpy as np

    rng = np.random.default_rng(7)
    count = 50
    starts = rng.uniform(0, 360, count).round(3)
    starts[:3] = (0.125, 359.995, 10.005)  # halves to even; past 359.995 wraps to 0
    ends = (starts + rng.uniform(0, 20, count)) % 360
    distances = rng.integers(-5, 70_000, (count, POINTS_PER_FRAME))
    intensities = rng.integers(-3, 300, (count, POINTS_PER_FRAME))
    stamps = rng.integers(0, 30_000, count)
    packed = encode_frames(3600, starts, ends, distances, intensities, stamps)
    one_by_one = b"".join(
        encode_frame(
            3600,
            float(starts[i]),
            float(ends[i]),
            distances[i].tolist(),
            intensities[i].tolist(),
            int(stamps[i]),
        )
        for i in range(count)
    )
    assert packed == one_by_one
