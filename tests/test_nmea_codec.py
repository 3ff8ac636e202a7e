"""NMEA-0183 codec properties: what the encoder writes comes back as the same fix, and any
bytes at all are either a checked sentence or dropped and counted, never an exception."""

from __future__ import annotations

import datetime as dt

from hypothesis import given, settings
from hypothesis import strategies as st

from brasidas.codecs.nmea import EpochAssembler, NmeaDecoder, sentence

FAST = settings(max_examples=80, deadline=None)


def ddmm(degrees: float, width: int) -> str:
    whole = int(abs(degrees))
    minutes = round((abs(degrees) - whole) * 60.0, 5)
    if minutes >= 60.0:
        whole, minutes = whole + 1, 0.0
    return f"{whole:0{width}d}{minutes:08.5f}"


def epoch_bytes(lat: float, lon: float, alt: float, knots: float, utc: dt.datetime) -> bytes:
    """One u-blox epoch (RMC, then GGA) for these values."""
    hhmmss = f"{utc:%H%M%S}.{utc.microsecond // 10000:02d}"
    ns, ew = ("N" if lat >= 0 else "S"), ("E" if lon >= 0 else "W")
    position = f"{ddmm(lat, 2)},{ns},{ddmm(lon, 3)},{ew}"
    return sentence(f"GPRMC,{hhmmss},A,{position},{knots:.3f},,{utc:%d%m%y},,,A") + sentence(
        f"GPGGA,{hhmmss},{position},1,09,0.95,{alt:.1f},M,34.0,M,,"
    )


latitudes = st.floats(-89.9, 89.9, allow_nan=False)
longitudes = st.floats(-179.9, 179.9, allow_nan=False)
altitudes = st.floats(-400.0, 9000.0, allow_nan=False)
speeds = st.floats(0.0, 200.0, allow_nan=False)
# Two-digit years: pynmea2 reads 69-99 as 19xx (GPS dates start in 1980).
times = st.datetimes(dt.datetime(2000, 1, 1), dt.datetime(2068, 12, 31)).map(
    lambda t: t.replace(microsecond=t.microsecond // 10000 * 10000)
)


@FAST
@given(latitudes, longitudes, altitudes, speeds, times)
def test_an_encoded_epoch_decodes_to_the_same_fix(
    lat: float, lon: float, alt: float, knots: float, utc: dt.datetime
) -> None:
    decoder, assembler = NmeaDecoder(), EpochAssembler()
    # Two epochs a second apart: the first teaches the assembler where a cycle ends.
    second = utc + dt.timedelta(seconds=1)
    data = epoch_bytes(lat, lon, alt, knots, utc) + epoch_bytes(lat, lon, alt, knots, second)
    fixes = [fix for msg in decoder.feed(data) for fix in assembler.feed(msg, 0.0)]
    fixes += assembler.poll(10.0)
    assert len(fixes) == 2
    assert all(fix is not None for fix in fixes)
    assert decoder.dropped == dict.fromkeys(decoder.dropped, 0)
    assert decoder.sentences == 4
    for fix, when in zip(fixes, (utc, second), strict=True):
        assert fix is not None
        assert abs(fix.latitude - lat) < 1e-6
        assert abs(fix.longitude - lon) < 1e-6
        assert fix.altitude_m is not None
        assert abs(fix.altitude_m - alt) <= 0.05 + 1e-9
        assert fix.speed_mps is not None
        assert abs(fix.speed_mps - knots * 1852 / 3600) < 1e-3
        assert fix.quality == 1
        assert fix.satellites == 9
        assert fix.hdop == 0.95
        assert fix.time.startswith(when.strftime("%Y-%m-%dT%H:%M:%S"))


@FAST
@given(st.lists(st.binary(max_size=200), max_size=12))
def test_arbitrary_bytes_never_raise_and_every_line_is_accounted_for(chunks: list[bytes]) -> None:
    decoder, assembler = NmeaDecoder(), EpochAssembler()
    for chunk in chunks:
        for msg in decoder.feed(chunk):
            assembler.feed(msg, 0.0)  # whatever the decoder lets through, the assembler takes
    assembler.poll(10.0)
    assert decoder.sentences >= 0
    assert all(count >= 0 for count in decoder.dropped.values())
    assert sum(decoder.by_type.values()) == decoder.sentences


valid = st.builds(
    epoch_bytes, latitudes, longitudes, altitudes, speeds, times.map(lambda t: t)
).map(lambda data: data[: data.index(b"\n") + 1])  # the RMC line


@FAST
@given(valid, st.data())
def test_a_corrupted_byte_is_dropped_and_counted_or_harmless(
    line: bytes, data: st.DataObject
) -> None:
    index = data.draw(st.integers(0, len(line) - 3), label="index")  # not the line end
    value = data.draw(st.integers(0, 255).filter(lambda b: b != line[index]), label="byte")
    mutated = line[:index] + bytes([value]) + line[index + 1 :]
    clean = NmeaDecoder().feed(line)
    decoder = NmeaDecoder()
    out = decoder.feed(mutated + b"\r\n")
    dropped = sum(decoder.dropped.values())
    if out:
        # Only a change the checksum cannot see may pass: the hex digits' letter case.
        assert len(out) == 1
        assert str(out[0]) == str(clean[0])
        assert mutated[index : index + 1].lower() == line[index : index + 1].lower()
    else:
        assert dropped >= 1 or decoder.sentences == 1  # counted either way


@FAST
@given(st.binary(max_size=300), st.integers(1, 16))
def test_chunking_does_not_change_what_is_decoded(noise: bytes, size: int) -> None:
    stream = noise + epoch_bytes(48.1, 11.5, 520.0, 3.0, dt.datetime(2024, 5, 1, 12)) + noise
    whole = NmeaDecoder()
    expected = [str(msg) for msg in whole.feed(stream)]
    chunked = NmeaDecoder()
    got = [
        str(msg) for i in range(0, len(stream), size) for msg in chunked.feed(stream[i : i + size])
    ]
    assert got == expected
    assert chunked.sentences == whole.sentences
    assert chunked.by_type == whole.by_type
