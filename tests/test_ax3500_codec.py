"""The AX3500 serial codec (sans-IO): command encoding, velocity mapping, line parsing, replies."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from brasidas.codecs import ax3500
from brasidas.codecs.ax3500 import Exchange, Kind, LineParser, MotionMapping, Reply, Status
from platformd.sim.ax3500 import Ax3500Device, SimOptions

# --------------------------------------------------------------------------- encoding


def test_motor_commands_are_two_uppercase_hex_digits() -> None:
    assert ax3500.motor(1, 0).encode() == b"!A00\r"
    assert ax3500.motor(1, 127).encode() == b"!A7F\r"
    assert ax3500.motor(1, -5).encode() == b"!a05\r"  # never "!a5"
    assert ax3500.motor(2, 10).encode() == b"!B0A\r"
    assert ax3500.motor(2, -127).encode() == b"!b7F\r"
    with pytest.raises(ValueError):
        ax3500.motor(1, 128)
    with pytest.raises(ValueError):
        ax3500.motor(3, 0)


def test_other_commands() -> None:
    assert ax3500.output("C", True).encode() == b"!C\r"
    assert ax3500.output("c", False).encode() == b"!c\r"
    assert ax3500.query("e") == ax3500.Command("?e", Kind.QUERY, 2)
    assert ax3500.query("i").values == 3
    assert ax3500.config_read(ax3500.PARAM_CONTROLLER_ID).encode() == b"^8A\r"
    assert ax3500.config_write(ax3500.PARAM_MOTOR_MODE, 1).encode() == b"^01 01\r"
    assert ax3500.reset().encode() == b"%rrrrrr\r"


def test_velocity_mapping_exact_levels() -> None:
    mapping = MotionMapping()
    assert [c.text for c in mapping.commands(0.5, -0.25)] == ["!A40", "!b20"]
    assert [c.text for c in mapping.commands(1.0, 1.0)] == ["!A7F", "!B7F"]
    assert [c.text for c in mapping.commands(-1.0, 0.0)] == ["!a7F", "!B00"]
    assert [c.text for c in mapping.commands(float("nan"), float("inf"))] == ["!A00", "!B00"]
    scaled = MotionMapping(linear_scale=0.5, angular_limit=0.2, invert_angular=True)
    assert scaled.levels(1.0, 1.0) == (64, -25)
    assert MotionMapping(invert_linear=True).levels(0.5, 0.0) == (-64, 0)


finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
fraction = st.floats(min_value=0.0, max_value=1.0)


@given(
    linear=st.floats(allow_nan=True),
    angular=st.floats(allow_nan=True),
    linear_scale=fraction,
    angular_scale=fraction,
    linear_limit=st.floats(min_value=-1.0, max_value=2.0),
    angular_limit=st.floats(min_value=-1.0, max_value=2.0),
    invert_linear=st.booleans(),
    invert_angular=st.booleans(),
)
def test_any_velocity_maps_to_valid_commands(
    linear: float,
    angular: float,
    linear_scale: float,
    angular_scale: float,
    linear_limit: float,
    angular_limit: float,
    invert_linear: bool,
    invert_angular: bool,
) -> None:
    mapping = MotionMapping(
        linear_scale, angular_scale, linear_limit, angular_limit, invert_linear, invert_angular
    )
    one, two = mapping.levels(linear, angular)
    for level, scale, limit in (
        (one, linear_scale, linear_limit),
        (two, angular_scale, angular_limit),
    ):
        assert abs(level) <= min(scale, max(0.0, min(1.0, limit))) * 127 + 0.5
    first, second = mapping.commands(linear, angular)
    assert first.text[:2] in ("!A", "!a")
    assert second.text[:2] in ("!B", "!b")
    for command in (first, second):
        digits = command.text[2:]
        assert len(digits) == 2
        assert digits == digits.upper()
        assert int(digits, 16) <= 0x7F


@given(linear=st.floats(min_value=-1.0, max_value=1.0), angular=st.floats(-1.0, 1.0))
def test_mapping_keeps_sign_and_inversion_flips_it(linear: float, angular: float) -> None:
    plain = MotionMapping().levels(linear, angular)
    flipped = MotionMapping(invert_linear=True, invert_angular=True).levels(linear, angular)
    assert flipped == (-plain[0], -plain[1])
    assert plain[0] == 0 or (plain[0] > 0) == (linear > 0)


# --------------------------------------------------------------------------- conversions


def test_unit_conversions_follow_the_manual() -> None:
    assert ax3500.battery_raw(24.0) == 0x70  # "24 V ≈ 0x70"
    assert ax3500.battery_volts(0x70) == pytest.approx(24.06, abs=0.01)
    assert ax3500.internal_volts(ax3500.internal_raw(12.0)) == pytest.approx(12.0, abs=0.1)
    assert ax3500.motor_amps(0x14) == 10.0
    assert ax3500.amps_raw(10.0) == 0x14
    assert ax3500.heatsink_celsius(153) == 25.0  # "25 °C ≈ 153"
    assert ax3500.heatsink_celsius(255) == -40.0
    assert ax3500.heatsink_celsius(0) == 150.0
    assert 25.0 < ax3500.heatsink_celsius(150) < 30.0


@given(st.floats(min_value=-40.0, max_value=150.0))
def test_heatsink_round_trip_within_a_step(celsius: float) -> None:
    assert abs(ax3500.heatsink_celsius(ax3500.heatsink_raw(celsius)) - celsius) < 2.5


@given(st.integers(0, 255), st.integers(0, 255))
def test_heatsink_lower_reading_is_hotter(a: int, b: int) -> None:
    if a < b:
        assert ax3500.heatsink_celsius(a) >= ax3500.heatsink_celsius(b)


# --------------------------------------------------------------------------- parsing


def test_lines_end_with_cr_or_lf_and_w_is_stripped() -> None:
    parser = LineParser()
    assert parser.feed(b"!A1") == []
    assert parser.feed(b"0\rW+\r\n") == ["!A10", "+"]
    assert parser.feed(b"WW?e\n7W0\r6C\r") == ["?e", "70", "6C"]
    assert parser.watchdog_chars == 4


def test_garbage_is_dropped_and_counted() -> None:
    parser = LineParser(max_line=8)
    assert parser.feed(b"\x00\xff!A\r+\r") == ["+"]
    assert parser.feed(b"0123456789ABCDEF\rOK\r") == ["OK"]
    assert parser.dropped_lines == 2


@given(st.lists(st.binary(max_size=40), max_size=20))
def test_parser_never_fails_and_yields_printable_lines(chunks: list[bytes]) -> None:
    parser = LineParser()
    for chunk in chunks:
        for line in parser.feed(chunk):
            assert line
            assert "W" not in line
            assert line.isprintable()
            assert len(line) <= 64


@given(st.binary(max_size=60), st.integers(1, 10))
def test_chunking_does_not_change_the_lines(data: bytes, size: int) -> None:
    whole = LineParser().feed(data + b"\r")
    parser = LineParser()
    pieces: list[str] = []
    for start in range(0, len(data), size):
        pieces += parser.feed(data[start : start + size])
    pieces += parser.feed(b"\r")
    assert pieces == whole


def _run(command: ax3500.Command, wire: bytes) -> tuple[ax3500.Reply | None, Exchange]:
    exchange = Exchange(command)
    reply = None
    for line in LineParser().feed(wire):
        reply = exchange.feed_line(line)
        if reply is not None:
            break
    return reply, exchange


def test_exchange_runtime_ack_and_nak() -> None:
    reply, _ = _run(ax3500.motor(1, 16), b"!A10\r+\r")
    assert reply is not None
    assert reply.status is Status.ACK
    assert reply.ok
    reply, _ = _run(ax3500.motor(1, 16), b"!A10\r-\r")
    assert reply is not None
    assert reply.status is Status.NAK
    assert not reply.ok


def test_exchange_skips_what_came_before_its_echo() -> None:
    # A late answer to a timed-out command, a banner and a config read's extra line.
    reply, exchange = _run(ax3500.motor(2, -1), b"+\rOK\r00\r!b01\r+\r")
    assert reply is not None
    assert reply.status is Status.ACK
    assert exchange.stray == ["+", "OK", "00"]


def test_exchange_query_values_in_either_case() -> None:
    reply, _ = _run(ax3500.query("m"), b"?m\r9a\rA0\r")
    assert reply is not None
    assert reply.values == (0x9A, 0xA0)
    reply, _ = _run(ax3500.query("t"), b"?t\r-\r")
    assert reply is not None
    assert reply.status is Status.NAK
    reply, _ = _run(ax3500.config_read(0), b"^00\r02\r")
    assert reply is not None
    assert reply.values == (2,)
    reply, _ = _run(ax3500.reset(), b"%rrrrrr\r")
    assert reply is not None
    assert reply.status is Status.ECHOED


def test_incomplete_answer_is_no_reply() -> None:
    assert _run(ax3500.query("e"), b"?e\r70\r")[0] is None
    assert _run(ax3500.motor(1, 0), b"!A0")[0] is None  # truncated echo


@given(st.lists(st.sampled_from(["+", "-", "OK", "00", "7F", ":0000", "junk", "!A10"]), max_size=8))
def test_exchange_never_answers_before_its_echo(lines: list[str]) -> None:
    exchange = Exchange(ax3500.motor(1, 0x20))
    for line in lines:
        assert exchange.feed_line(line) is None or exchange.echoed


# ------------------------------------------------------------------ round trips through the device


def _exchange(device: Ax3500Device, command: ax3500.Command, chunk: int, noise: bytes) -> Reply:
    """Send ``command`` to the simulated controller; its answer, with watchdog ``W``s mixed in
    and cut into ``chunk``-byte pieces, goes through the host's parser and exchange."""
    wire = device.feed(command.encode(), 0.0)
    wire = noise + b"W".join(wire[i : i + chunk] for i in range(0, len(wire), chunk))
    parser, exchange = LineParser(), Exchange(command)
    for start in range(0, len(wire), chunk):
        for line in parser.feed(wire[start : start + chunk]):
            reply = exchange.feed_line(line)
            if reply is not None:
                return reply
    raise AssertionError(f"no reply to {command.text} in {wire!r}")


noise_lines = st.lists(st.sampled_from([b"OK\r", b"+\r", b"7F\r", b"\x00\xff\r", b"W"]), max_size=3)


@given(
    st.integers(1, 2),
    st.integers(-127, 127),
    st.integers(1, 8),
    noise_lines.map(b"".join),
    st.booleans(),
)
def test_a_motor_command_round_trips_through_the_controller(
    channel: int, level: int, chunk: int, noise: bytes, lowercase: bool
) -> None:
    device = Ax3500Device(SimOptions(lowercase_hex=lowercase))
    device.power_up(0.0)
    device.mixed = False
    reply = _exchange(device, ax3500.motor(channel, level), chunk, noise)
    assert reply.status is Status.ACK
    assert device.channels[channel - 1] == level
    # ... and the controller reports the power it applies.
    reply = _exchange(device, ax3500.query("v"), chunk, b"")
    assert reply.status is Status.VALUES
    assert reply.values[channel - 1] == abs(level)


@given(st.integers(0, 255), st.integers(0, 255), st.integers(1, 8), st.booleans())
def test_a_config_write_reads_back(parameter: int, value: int, chunk: int, lowercase: bool) -> None:
    device = Ax3500Device(SimOptions(lowercase_hex=lowercase))
    device.power_up(0.0)
    assert _exchange(device, ax3500.config_write(parameter, value), chunk, b"").ok
    reply = _exchange(device, ax3500.config_read(parameter), chunk, b"")
    assert reply.status is Status.VALUES
    assert reply.values == (value,)
