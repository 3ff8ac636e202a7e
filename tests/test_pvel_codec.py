"""The ``$PVEL`` codec: exact bytes, checksum, tags, and property-based round trips."""

from __future__ import annotations

import os

from hypothesis import given
from hypothesis import strategies as st

from brasidas.codecs import pvel
from brasidas.codecs.pvel import DropReason, PvelEncoder, PvelSentence

KEY = bytes(range(32))
velocities = st.floats(min_value=-1.0, max_value=1.0, allow_nan=False)
counts = st.integers(min_value=0, max_value=pvel.MAX_COUNT)


def nmea(body: str) -> bytes:
    return f"${body}*{pvel.checksum(body.encode()):02X}".encode()


def test_exact_bytes_of_an_untagged_sentence() -> None:
    # Checksum worked independently: functools.reduce(operator.xor, b"PVEL,1,0.50000,-0.25000").
    assert pvel.encode(1, 0.5, -0.25) == b"$PVEL,1,0.50000,-0.25000*3D"
    # A published NMEA-0183 example sentence: $GPGLL,5057.970,N,00146.110,E,142451,A*27
    assert pvel.checksum(b"GPGLL,5057.970,N,00146.110,E,142451,A") == 0x27


def test_values_are_clamped_and_never_negative_zero() -> None:
    assert pvel.encode(7, 3.0, -1e-9) == nmea("PVEL,7,1.00000,0.00000")
    assert pvel.encode(8, float("nan"), -2) == nmea("PVEL,8,0.00000,-1.00000")


def test_tagged_sentence_has_sixteen_hex_digits_before_the_checksum() -> None:
    datagram = pvel.encode(42, 0.1, 0.2, key=KEY, session_id="s1")
    body = datagram[1 : datagram.index(b"*")].decode()
    fields = body.split(",")
    assert fields[:4] == ["PVEL", "42", "0.10000", "0.20000"]
    assert len(fields[4]) == 16
    assert fields[4] == fields[4].upper()
    sentence = pvel.decode(datagram)
    assert isinstance(sentence, PvelSentence)
    assert pvel.verify_tag(sentence, KEY, "s1")
    assert not pvel.verify_tag(sentence, KEY, "s2")
    assert not pvel.verify_tag(sentence, os.urandom(32), "s1")


def test_untagged_sentence_never_verifies() -> None:
    sentence = pvel.decode(pvel.encode(1, 0, 0))
    assert isinstance(sentence, PvelSentence)
    assert sentence.tag is None
    assert not pvel.verify_tag(sentence, KEY, "s1")


def test_tag_covers_the_values() -> None:
    datagram = pvel.encode(5, 0.1, 0.2, key=KEY, session_id="s")
    forged_body = datagram[1 : datagram.index(b"*")].replace(b"0.10000", b"0.90000")
    sentence = pvel.decode(b"$" + forged_body + f"*{pvel.checksum(forged_body):02X}".encode())
    assert isinstance(sentence, PvelSentence)
    assert sentence.x == 0.9
    assert not pvel.verify_tag(sentence, KEY, "s")


def test_drop_reasons() -> None:
    good = pvel.encode(3, 0.5, 0.5)
    assert isinstance(pvel.decode(good), PvelSentence)
    assert isinstance(pvel.decode(good + b"\r\n"), PvelSentence)
    assert pvel.decode(good[:-1] + (b"0" if good[-1:] != b"0" else b"1")) is (
        DropReason.BAD_CHECKSUM
    )
    assert pvel.decode(good.replace(b"PVEL,3", b"PVEL,4")) is DropReason.BAD_CHECKSUM
    assert pvel.decode(b"") is DropReason.MALFORMED
    assert pvel.decode(b"$PVEL,3,0.5,0.5") is DropReason.MALFORMED  # no checksum
    assert pvel.decode(good.replace(b"*", b"#")) is DropReason.MALFORMED
    assert pvel.decode(good[:-2] + b"ZZ") is DropReason.MALFORMED
    assert pvel.decode(good[:-2] + b"+F") is DropReason.MALFORMED
    assert pvel.decode(nmea("PVEL,3,0.5")) is DropReason.MALFORMED
    assert pvel.decode(nmea("PVEL,-3,0.5,0.5")) is DropReason.MALFORMED
    assert pvel.decode(nmea("PVEL,3,nan,0.5")) is DropReason.MALFORMED
    assert pvel.decode(nmea("PVEL,3,inf,0.5")) is DropReason.MALFORMED
    assert pvel.decode(nmea("PVEL,3,1e0,0.5")) is DropReason.MALFORMED
    assert pvel.decode(nmea("GPGGA,3,0.5,0.5")) is DropReason.MALFORMED
    assert pvel.decode(nmea("PVEL,3,0.5,0.5,XYZ")) is DropReason.MALFORMED
    assert pvel.decode(nmea("PVEL,3,0.5,0.5,00AB")) is DropReason.MALFORMED  # short tag
    assert pvel.decode(nmea("PVEL,3,0.5,0.5,123456789")) is DropReason.MALFORMED  # 9 digits
    assert pvel.decode(b"$" + "PVEL,3,é,0".encode() + b"*00") in (
        DropReason.MALFORMED,
        DropReason.BAD_CHECKSUM,
    )
    assert pvel.decode(nmea("PVEL,3,1.00001,0.5")) is DropReason.OUT_OF_RANGE
    assert pvel.decode(nmea("PVEL,3,0.5,-1.5")) is DropReason.OUT_OF_RANGE
    assert pvel.decode(nmea(f"PVEL,{pvel.MAX_COUNT + 1},0.5,0.5")) is DropReason.OUT_OF_RANGE
    assert pvel.decode(nmea("PVEL,3,0.5,0.5").ljust(200, b" ")) is DropReason.MALFORMED


def test_encoder_counts_up_and_tags_for_its_session() -> None:
    encoder = PvelEncoder(key=KEY, session_id="abc", start=10)
    sentences = [pvel.decode(encoder.encode(0.0, 0.0)) for _ in range(3)]
    assert [s.count for s in sentences if isinstance(s, PvelSentence)] == [10, 11, 12]
    assert all(isinstance(s, PvelSentence) and pvel.verify_tag(s, KEY, "abc") for s in sentences)


def test_exact_bytes_of_a_stamped_sentence_and_its_age() -> None:
    # The send time sits between the values and the tag, modulo 10^8 ms.
    assert pvel.encode(1, 0.5, -0.25, sent_ms=12_345_678) == nmea(
        "PVEL,1,0.50000,-0.25000,12345678"
    )
    datagram = pvel.encode(1, 0.5, -0.25, sent_ms=3 * pvel.SENT_MODULUS + 42)
    assert datagram == nmea("PVEL,1,0.50000,-0.25000,42")
    sentence = pvel.decode(datagram)
    assert isinstance(sentence, PvelSentence)
    assert sentence.sent_ms == 42
    assert pvel.age_ms(sentence, 3 * pvel.SENT_MODULUS + 42 + 150.5) == 150.5
    # Across the wrap: sent just before it, received just after.
    late = pvel.decode(pvel.encode(2, 0, 0, sent_ms=pvel.SENT_MODULUS - 10))
    assert isinstance(late, PvelSentence)
    assert pvel.age_ms(late, 5 * pvel.SENT_MODULUS + 20) == 30
    # An older sender's sentence has no send time, hence no known age.
    old = pvel.decode(pvel.encode(3, 0.1, 0.1))
    assert isinstance(old, PvelSentence)
    assert old.sent_ms is None
    assert pvel.age_ms(old, 1000.0) is None


def test_tag_covers_the_send_time() -> None:
    datagram = pvel.encode(5, 0.1, 0.2, key=KEY, session_id="s", sent_ms=1000)
    body = datagram[1 : datagram.index(b"*")]
    sentence = pvel.decode(datagram)
    assert isinstance(sentence, PvelSentence)
    assert pvel.verify_tag(sentence, KEY, "s")
    # An old packet made to look fresh, or its time stripped: neither verifies.
    for forged in (body.replace(b",1000,", b",9000,"), body.replace(b",1000,", b",")):
        result = pvel.decode(b"$" + forged + f"*{pvel.checksum(forged):02X}".encode())
        assert isinstance(result, PvelSentence)
        assert not pvel.verify_tag(result, KEY, "s")


@given(
    count=counts,
    x=velocities,
    z=velocities,
    tagged=st.booleans(),
    sent=st.none() | st.integers(min_value=0, max_value=2**53),
)
def test_round_trip(count: int, x: float, z: float, tagged: bool, sent: int | None) -> None:
    datagram = pvel.encode(count, x, z, key=KEY if tagged else None, session_id="s", sent_ms=sent)
    assert len(datagram) <= 64  # the seed's bound on a velocity packet's payload
    sentence = pvel.decode(datagram)
    assert isinstance(sentence, PvelSentence)
    assert sentence.count == count
    assert abs(sentence.x - x) <= 5e-6
    assert abs(sentence.z - z) <= 5e-6
    assert sentence.sent_ms == (None if sent is None else sent % pvel.SENT_MODULUS)
    assert pvel.verify_tag(sentence, KEY, "s") is tagged


@given(
    now=st.integers(min_value=0, max_value=2**53),
    age=st.integers(min_value=-pvel.SENT_MODULUS // 2, max_value=pvel.SENT_MODULUS // 2 - 1),
)
def test_age_is_exact_for_any_clock_and_any_age_within_half_the_wrap(now: int, age: int) -> None:
    sentence = pvel.decode(pvel.encode(1, 0, 0, sent_ms=now - age + pvel.SENT_MODULUS))
    assert isinstance(sentence, PvelSentence)
    assert pvel.age_ms(sentence, now + pvel.SENT_MODULUS) == age


@given(data=st.binary(max_size=160))
def test_arbitrary_bytes_never_raise(data: bytes) -> None:
    result = pvel.decode(data)
    if isinstance(result, PvelSentence):
        assert -1 <= result.x <= 1
        assert -1 <= result.z <= 1


@given(
    count=counts,
    x=velocities,
    z=velocities,
    position=st.integers(0, 200),
    flip=st.integers(1, 127),
    sent=st.none() | st.integers(min_value=0, max_value=2**40),
)
def test_any_single_corrupted_byte_is_dropped(
    count: int, x: float, z: float, position: int, flip: int, sent: int | None
) -> None:
    original = pvel.encode(count, x, z, key=KEY, session_id="s", sent_ms=sent)
    datagram = bytearray(original)
    datagram[position % len(datagram)] ^= flip
    result = pvel.decode(bytes(datagram))
    # The XOR checksum catches every single-byte change in the body; only a change of case in
    # the checksum's own hex digits still decodes, to the very same sentence.
    assert isinstance(result, DropReason) or result == pvel.decode(original)


@given(
    count=counts, x=velocities, z=velocities, cut=st.integers(0, 63), extra=st.binary(max_size=8)
)
def test_a_cut_or_padded_sentence_never_passes_as_another(
    count: int, x: float, z: float, cut: int, extra: bytes
) -> None:
    original = pvel.encode(count, x, z, key=KEY, session_id="s")
    expected = pvel.decode(original)
    for datagram in (original[: cut % len(original)], original.rstrip(b"\r\n") + extra):
        result = pvel.decode(datagram)
        # Dropped with a reason, or (only when the change left the sentence intact, e.g. a
        # different line end) the very same sentence; its tag still verifies only then.
        assert isinstance(result, DropReason) or result == expected
        if isinstance(result, PvelSentence):
            assert pvel.verify_tag(result, KEY, "s")
