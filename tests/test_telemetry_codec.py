"""The telemetry datagram codec: round trips, splitting, and every kind of bad datagram."""

from __future__ import annotations

import os

import msgpack
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brasidas.codecs.telemetry import (
    FLAG_AUTHENTICATED,
    MAX_DATAGRAM,
    REJECT_REASONS,
    TAG_LENGTH,
    VERSION,
    TelemetryDecodeError,
    TelemetryDecoder,
    TelemetryEncoder,
    parse,
)

KEY = bytes(range(32))

SNAPSHOT = {
    "mode": "teleop",
    "manual_override": True,
    "lights": {"main": True, "positional": False},
    "battery": {"volts": 24.3, "level": "high"},
    "gps": {"fix": True, "lat": 37.9838096, "lon": 23.7275388, "sats": 9, "hdop": 0.9},
    "attitude": {"roll": 1.5, "pitch": -0.25, "yaw": 271.0},
    "streams": {"navcam": "playing"},
    "autonomy": None,
}

json_scalars = (
    st.none()
    | st.booleans()
    | st.integers(-(2**63), 2**64 - 1)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(max_size=40)
)
json_values = st.recursive(
    json_scalars,
    lambda inner: (
        st.lists(inner, max_size=6) | st.dictionaries(st.text(max_size=12), inner, max_size=6)
    ),
    max_leaves=40,
)
snapshots = st.dictionaries(st.text(min_size=1, max_size=16), json_values, max_size=12)


def test_round_trip_in_one_datagram() -> None:
    encoder = TelemetryEncoder("rover-1", KEY)
    decoder = TelemetryDecoder("rover-1", KEY)
    (datagram,) = encoder.encode(SNAPSHOT, 1_700_000_000.25)
    assert len(datagram) < MAX_DATAGRAM
    assert datagram[0] == VERSION
    assert datagram[1] == FLAG_AUTHENTICATED
    (frame,) = decoder.feed(datagram)
    assert frame.sections == SNAPSHOT
    assert (frame.platform_id, frame.seq, frame.timestamp) == ("rover-1", 1, 1_700_000_000.25)
    assert frame.size == len(datagram)
    assert decoder.accepted == 1
    assert sum(decoder.rejected.values()) == 0


def test_insecure_stream_has_no_tag() -> None:
    (datagram,) = TelemetryEncoder("rover-1", None).encode(SNAPSHOT, 1.0)
    assert datagram[1] == 0
    (frame,) = TelemetryDecoder("rover-1", None).feed(datagram)
    assert frame.sections == SNAPSHOT
    # A station holding a session key refuses an unauthenticated stream.
    decoder = TelemetryDecoder("rover-1", KEY)
    assert decoder.feed(datagram) == []
    assert decoder.rejected["unauthenticated"] == 1


def test_large_snapshot_is_split_by_section_and_merges_back() -> None:
    big = {f"section{i}": {"values": list(range(i * 40, i * 40 + 60))} for i in range(12)}
    encoder = TelemetryEncoder("rover-1", KEY)
    datagrams = encoder.encode(big, 5.0)
    assert len(datagrams) > 1
    assert all(len(d) < MAX_DATAGRAM for d in datagrams)
    decoder = TelemetryDecoder("rover-1", KEY)
    merged: dict[str, object] = {}
    for datagram in datagrams:
        (frame,) = decoder.feed(datagram)
        merged.update(frame.sections)
    assert merged == big
    assert decoder.last_seq == len(datagrams)
    assert encoder.trimmed == 0


def test_a_split_keeps_the_pose_with_the_scan_drawn_around_it() -> None:
    """The scan's obstacles are relative to the robot: a split snapshot carries them in the
    datagram of the pose they are drawn around (one lost or late cannot pair them wrong)."""
    big = {f"section{i}": {"values": list(range(i * 40, i * 40 + 60))} for i in range(12)}
    lidar = {"pos": {"values": list(range(90))}, "per": {"o": [[1.0, 2.0, 0.3]] * 12}}
    lidar["lv"] = {"r": list(range(72))}
    for order in (big | lidar, lidar | big):
        datagrams = TelemetryEncoder("rover-1", KEY).encode(order, 5.0)
        decoder = TelemetryDecoder("rover-1", KEY)
        carrying = [set(f.sections) for d in datagrams for f in decoder.feed(d)]
        assert len(carrying) > 1
        assert any({"pos", "per", "lv"} <= keys for keys in carrying), carrying


def test_section_too_large_alone_is_trimmed_not_dropped() -> None:
    sections = {"huge": {"blob": "x" * 5000}, "small": {"ok": 1}}
    encoder = TelemetryEncoder("rover-1", KEY)
    datagrams = encoder.encode(sections, 5.0)
    assert all(len(d) < MAX_DATAGRAM for d in datagrams)
    decoder = TelemetryDecoder("rover-1", KEY)
    merged: dict[str, object] = {}
    for datagram in datagrams:
        merged.update(decoder.decode(datagram).sections)
    assert merged["small"] == {"ok": 1}
    assert merged["huge"]["!"].startswith("trimmed: 50")  # the section's error, sized
    assert encoder.trimmed == 1


def test_values_are_made_json_compatible() -> None:
    encoder = TelemetryEncoder("rover-1", KEY)
    (datagram,) = encoder.encode({"a": (1, 2), "b": float("nan"), "c": {3: "x"}}, 0.0)
    sections = TelemetryDecoder("rover-1", KEY).decode(datagram).sections
    assert sections == {"a": [1, 2], "b": None, "c": {"3": "x"}}


def test_forged_tag_and_wrong_key_are_refused() -> None:
    (datagram,) = TelemetryEncoder("rover-1", KEY).encode(SNAPSHOT, 1.0)
    decoder = TelemetryDecoder("rover-1", KEY)
    flipped = bytearray(datagram)
    flipped[10] ^= 0x01
    assert decoder.feed(bytes(flipped)) == []
    (other,) = TelemetryEncoder("rover-1", os.urandom(32)).encode(SNAPSHOT, 1.0)
    assert decoder.feed(other) == []
    assert decoder.rejected["forged"] == 2
    assert decoder.feed(datagram) != []  # the genuine one still passes afterwards


def test_replayed_and_old_sequence_numbers_are_refused() -> None:
    encoder = TelemetryEncoder("rover-1", KEY)
    first = encoder.encode(SNAPSHOT, 1.0)[0]
    second = encoder.encode(SNAPSHOT, 1.2)[0]
    decoder = TelemetryDecoder("rover-1", KEY)
    assert decoder.feed(second) != []
    assert decoder.feed(second) == []  # replay
    assert decoder.feed(first) == []  # older than the last accepted
    assert decoder.rejected["replayed"] == 2
    assert decoder.accepted == 1


def test_truncated_wrong_version_and_wrong_platform() -> None:
    encoder = TelemetryEncoder("rover-1", KEY)
    (datagram,) = encoder.encode(SNAPSHOT, 1.0)
    decoder = TelemetryDecoder("rover-1", KEY)
    for cut in (0, 1, 2, TAG_LENGTH + 2, len(datagram) // 2, len(datagram) - 1):
        assert decoder.feed(datagram[:cut]) == []
    # Too short to hold a tag: truncated; long enough: the tag no longer matches.
    assert decoder.rejected["truncated"] == 4
    assert decoder.rejected["forged"] == 2
    assert decoder.feed(bytes([VERSION + 1]) + datagram[1:]) == []
    assert decoder.rejected["version"] == 1
    (elsewhere,) = TelemetryEncoder("rover-2", KEY).encode(SNAPSHOT, 1.0)
    assert decoder.feed(elsewhere) == []
    assert decoder.rejected["wrong_platform"] == 1


def test_authentic_but_malformed_content_is_garbage() -> None:
    decoder = TelemetryDecoder("rover-1", None)
    cases = [
        msgpack.packb(["rover-1", 1, 1.0]),  # three items
        msgpack.packb(["rover-1", -1, 1.0, {}]),  # negative seq
        msgpack.packb(["rover-1", 1, "now", {}]),  # timestamp type
        msgpack.packb(["rover-1", 1, 1.0, {"a": b"\x00"}]),  # bytes are not JSON
        msgpack.packb(["rover-1", 1, 1.0, {"a": float("inf")}]),
        msgpack.packb(["rover-1", 1, 1.0, {}]) + b"\x00",  # trailing bytes
    ]
    for packed in cases:
        with pytest.raises(TelemetryDecodeError) as info:
            decoder.decode(bytes((VERSION, 0)) + packed)
        assert info.value.reason == "garbage"


@settings(max_examples=50, deadline=None)  # ~0.2 s to draw each: the suite stays fast
@given(snapshots, st.floats(0, 4e9), st.integers(0, 2**40))
def test_any_snapshot_round_trips_within_the_size_limit(
    sections: dict[str, object], timestamp: float, first_seq: int
) -> None:
    encoder = TelemetryEncoder("rover-1", KEY, first_seq=first_seq)
    decoder = TelemetryDecoder("rover-1", KEY)
    merged: dict[str, object] = {}
    for datagram in encoder.encode(sections, timestamp):
        assert len(datagram) < MAX_DATAGRAM
        frame = decoder.decode(datagram)
        assert frame.timestamp == timestamp
        merged.update(frame.sections)
    if encoder.trimmed == 0:
        assert merged == sections
    else:
        assert set(merged) == set(sections)


@settings(max_examples=500, deadline=None)
@given(st.binary(max_size=1400), st.sampled_from([KEY, None]))
def test_random_bytes_only_ever_raise_the_codec_error(data: bytes, key: bytes | None) -> None:
    try:
        frame = parse(data, key)
    except TelemetryDecodeError as err:
        assert err.reason in REJECT_REASONS
        frame = None
    decoder = TelemetryDecoder("rover-1", key)
    frames = decoder.feed(data)
    assert len(frames) + sum(decoder.rejected.values()) == 1
    if frame is None:
        assert frames == []


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=600))
def test_random_msgpack_bodies_in_an_insecure_frame_never_crash(body: bytes) -> None:
    decoder = TelemetryDecoder("rover-1", None)
    datagram = bytes((VERSION, 0)) + body
    frames = decoder.feed(datagram)
    assert len(frames) + sum(decoder.rejected.values()) == 1


@settings(max_examples=200, deadline=None)
@given(st.binary(min_size=1, max_size=64), st.integers(0, 200))
def test_tampering_anywhere_is_refused(noise: bytes, where: int) -> None:
    (datagram,) = TelemetryEncoder("rover-1", KEY).encode(SNAPSHOT, 1.0)
    where %= len(datagram)
    tampered = bytearray(datagram)
    for i, byte in enumerate(noise):
        if where + i < len(tampered):
            tampered[where + i] ^= byte or 0xFF
    decoder = TelemetryDecoder("rover-1", KEY)
    assert decoder.feed(bytes(tampered)) == []


@settings(max_examples=200, deadline=None)
@given(st.data())
def test_a_changed_byte_in_an_authenticated_datagram_is_refused_and_counted(
    data: st.DataObject,
) -> None:
    (datagram,) = TelemetryEncoder("rover-1", KEY).encode(SNAPSHOT, 1.0)
    position = data.draw(st.integers(0, len(datagram) - 1), label="position")
    flip = data.draw(st.integers(1, 255), label="flip")
    changed = bytearray(datagram)
    changed[position] ^= flip
    decoder = TelemetryDecoder("rover-1", KEY)
    assert decoder.feed(bytes(changed)) == []
    assert decoder.accepted == 0
    assert sum(decoder.rejected.values()) == 1
    # Cut short anywhere: refused and counted too.
    cut = data.draw(st.integers(0, len(datagram) - 1), label="cut")
    assert decoder.feed(datagram[:cut]) == []
    assert sum(decoder.rejected.values()) == 2
