"""Roboteq AX3500 serial protocol (``../shared/hardware.md``), sans-IO.

Commands are short ASCII strings ended by ``\\r``; the controller echoes every character, so
the first line back is the command itself, then:

- run-time ``!`` commands and config writes ``^mm nn`` answer ``+`` (done) or ``-`` (refused);
- queries ``?x`` answer one line of two hex digits per value (or ``-`` for an unknown query);
- config reads ``^mm`` answer one hex line (some units send one extra line: tolerated);
- ``%rrrrrr`` (reset) answers nothing but its echo, then a restart banner and ``OK``.

Unsolicited ``W`` characters (the watchdog) may appear anywhere and are stripped. Lines end
with ``\\r`` or ``\\n``; empty lines are skipped.

:class:`LineParser` turns bytes into lines; :class:`Exchange` matches the lines of one
command in flight (echo, then its answer); :class:`MotionMapping` turns a platform-agnostic
velocity into the two mixed-mode channel commands.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from enum import Enum

MAX_VALUE = 0x7F
"""A channel command's magnitude: 7F = 100 %."""
MAX_LEVEL = MAX_VALUE
RESET = "%rrrrrr"
BANNER_OK = "OK"
CR = b"\r"

PARAM_INPUT_MODE = 0x00
"""Config ``^00``: 00 R/C, 01 RS-232 without watchdog, 02 RS-232 with watchdog, 03 analog."""
PARAM_MOTOR_MODE = 0x01
"""Config ``^01``: 01 = mixed mode, open loop (channel 1 speed, channel 2 steering)."""
PARAM_CONTROLLER_ID = 0x8A
"""Config ``^8A``: bit 3 set on an AX3500."""
INPUT_MODE_RC = 0x00
INPUT_MODE_RS232 = 0x01
INPUT_MODE_RS232_WATCHDOG = 0x02
INPUT_MODE_ANALOG = 0x03
MOTOR_MODE_MIXED_OPEN_LOOP = 0x01
CONTROLLER_ID_AX3500_BIT = 0x08

QUERY_VALUES: dict[str, int] = {
    "v": 2,  # power applied to motors 1, 2
    "a": 2,  # motor amps x 2
    "e": 2,  # main battery, internal 12 V
    "m": 2,  # heatsink thermistors
    "p": 2,  # analog inputs 1, 2
    "r": 2,  # analog inputs 3, 4
    "i": 3,  # digital inputs E, F, emergency stop
}
"""Valid queries and how many value lines each answers."""

THERMISTOR_TABLE: tuple[int, ...] = (
    248, 246, 243, 240, 235, 230, 224, 217, 208, 199, 188, 177, 165, 153, 140, 128, 116, 104,
    93, 83, 74, 65, 58, 51, 45, 40, 35, 31, 27, 24, 21, 19, 17, 15, 13, 12, 11, 9, 8,
)  # fmt: skip
"""``?m`` readings from -40 °C to 150 °C in 5 °C steps (lower = hotter)."""
THERMISTOR_FIRST_C = -40.0
THERMISTOR_STEP_C = 5.0

_HEX2 = re.compile(r"[0-9A-Fa-f]{2}")


# --------------------------------------------------------------------------- commands


class Kind(Enum):
    RUNTIME = "runtime"
    """``!``: answers ``+``/``-``."""
    QUERY = "query"
    """``?x``: answers value lines."""
    CONFIG_READ = "config_read"
    """``^mm``: answers one value line."""
    CONFIG_WRITE = "config_write"
    """``^mm nn``: answers ``+``/``-``."""
    RESET = "reset"
    """``%rrrrrr``: echo only, then the restart banner."""


@dataclass(frozen=True)
class Command:
    """One command as sent (without its ``\\r``) and what its answer looks like."""

    text: str
    kind: Kind
    values: int = 0
    """Value lines expected after the echo (queries and config reads)."""

    def encode(self) -> bytes:
        return self.text.encode("ascii") + CR


def motor(channel: int, level: int) -> Command:
    """Channel 1 or 2 at ``level`` in [-127, 127]: ``!A``/``!a`` (1) or ``!B``/``!b`` (2)."""
    if channel not in (1, 2):
        raise ValueError(f"channel must be 1 or 2, not {channel}")
    if not -MAX_LEVEL <= level <= MAX_LEVEL:
        raise ValueError(f"level must be in [-127, 127], not {level}")
    letter = "A" if channel == 1 else "B"
    if level < 0:
        letter = letter.lower()
    return Command(f"!{letter}{abs(level):02X}", Kind.RUNTIME)


def output(name: str, on: bool) -> Command:
    """Accessory output ``name`` (``C``) on (``!C``) or off (``!c``)."""
    if len(name) != 1 or not name.isalpha():
        raise ValueError(f"output must be one letter, not {name!r}")
    return Command(f"!{name.upper() if on else name.lower()}", Kind.RUNTIME)


def query(letter: str) -> Command:
    """``?e``, ``?m``, ``?a``, ... (unknown letters are sent too: the controller says ``-``)."""
    return Command(f"?{letter}", Kind.QUERY, QUERY_VALUES.get(letter, 1))


def config_read(parameter: int) -> Command:
    return Command(f"^{parameter:02X}", Kind.CONFIG_READ, 1)


def config_write(parameter: int, value: int) -> Command:
    return Command(f"^{parameter:02X} {value:02X}", Kind.CONFIG_WRITE)


def reset() -> Command:
    return Command(RESET, Kind.RESET)


# --------------------------------------------------------------------------- velocity mapping


@dataclass(frozen=True)
class MotionMapping:
    """Velocity (linear x, angular z in [-1, 1]) to the mixed-mode channel levels.

    Each component is clamped to [-1, 1], scaled, clipped to its limit, inverted when the
    chassis is wired the other way round, then rounded to a level in [-127, 127]. Channel 1
    is the common speed, channel 2 the steering: a left turn (positive z) is ``!B`` unless
    ``invert_angular``.
    """

    linear_scale: float = 1.0
    angular_scale: float = 1.0
    linear_limit: float = 1.0
    angular_limit: float = 1.0
    invert_linear: bool = False
    invert_angular: bool = False

    def levels(self, linear: float, angular: float) -> tuple[int, int]:
        return (
            _level(linear, self.linear_scale, self.linear_limit, self.invert_linear),
            _level(angular, self.angular_scale, self.angular_limit, self.invert_angular),
        )

    def commands(self, linear: float, angular: float) -> tuple[Command, Command]:
        channel1, channel2 = self.levels(linear, angular)
        return motor(1, channel1), motor(2, channel2)


def _level(value: float, scale: float, limit: float, invert: bool) -> int:
    if not math.isfinite(value):  # NaN or inf from a confused source: stand still
        return 0
    value = max(-1.0, min(1.0, value)) * scale
    bound = max(0.0, min(1.0, limit))
    value = max(-bound, min(bound, value))
    if invert:
        value = -value
    level = round(value * MAX_LEVEL)
    return max(-MAX_LEVEL, min(MAX_LEVEL, level))


# --------------------------------------------------------------------------- unit conversions


def battery_volts(raw: int) -> float:
    """``?e`` first value: main battery volts."""
    return 55.0 * raw / 256.0


def internal_volts(raw: int) -> float:
    """``?e`` second value: internal 12 V supply."""
    return 28.5 * raw / 256.0


def battery_raw(volts: float) -> int:
    return _byte(round(volts * 256.0 / 55.0))


def internal_raw(volts: float) -> int:
    return _byte(round(volts * 256.0 / 28.5))


def motor_amps(raw: int) -> float:
    """``?a`` value: amps = raw / 2."""
    return raw / 2.0


def amps_raw(amps: float) -> int:
    return _byte(round(abs(amps) * 2.0))


def heatsink_celsius(raw: int) -> float:
    """``?m`` value to °C, interpolated in the thermistor table (clamped at its ends)."""
    table = THERMISTOR_TABLE
    if raw >= table[0]:
        return THERMISTOR_FIRST_C
    if raw <= table[-1]:
        return THERMISTOR_FIRST_C + THERMISTOR_STEP_C * (len(table) - 1)
    for index in range(len(table) - 1):
        high, low = table[index], table[index + 1]
        if low <= raw <= high:
            fraction = (high - raw) / (high - low)
            return THERMISTOR_FIRST_C + THERMISTOR_STEP_C * (index + fraction)
    raise AssertionError("unreachable: the table is monotonic")


def heatsink_raw(celsius: float) -> int:
    """°C to the ``?m`` reading (the inverse of :func:`heatsink_celsius`)."""
    table = THERMISTOR_TABLE
    position = (celsius - THERMISTOR_FIRST_C) / THERMISTOR_STEP_C
    if position <= 0:
        return table[0]
    if position >= len(table) - 1:
        return table[-1]
    index = int(position)
    fraction = position - index
    return round(table[index] - (table[index] - table[index + 1]) * fraction)


def _byte(value: int) -> int:
    return max(0, min(0xFF, value))


# --------------------------------------------------------------------------- reading


class LineParser:
    """Bytes from the controller to lines: ``W`` stripped, ``\\r``/``\\n`` ends, junk counted.

    A line longer than ``max_line`` is garbage (no reply is that long): it is dropped and
    counted, and the parser resynchronises at the next line end.
    """

    def __init__(self, max_line: int = 64) -> None:
        self.max_line = max_line
        self.watchdog_chars = 0
        """Stray ``W`` characters stripped."""
        self.dropped_lines = 0
        """Overlong or non-ASCII lines dropped."""
        self._buffer = bytearray()
        self._junk = False

    def feed(self, data: bytes) -> list[str]:
        lines: list[str] = []
        for byte in data:
            if byte in (0x0D, 0x0A):
                if self._junk:
                    self.dropped_lines += 1
                elif self._buffer:
                    lines.append(self._buffer.decode("ascii"))
                self._buffer.clear()
                self._junk = False
            elif byte == 0x57:  # "W": the watchdog, anywhere in the stream
                self.watchdog_chars += 1
            elif self._junk:
                continue
            elif byte < 0x20 or byte > 0x7E or len(self._buffer) >= self.max_line:
                self._junk = True
                self._buffer.clear()
            else:
                self._buffer.append(byte)
        return lines

    def clear(self) -> None:
        """Forget a partial line (after a reset or a reconnect)."""
        self._buffer.clear()
        self._junk = False


class Status(Enum):
    ACK = "+"
    NAK = "-"
    VALUES = "values"
    """A query or config read answered with its values."""
    ECHOED = "echoed"
    """A reset: the echo is all there is."""


@dataclass(frozen=True)
class Reply:
    command: Command
    status: Status
    values: tuple[int, ...] = ()

    @property
    def ok(self) -> bool:
        return self.status is not Status.NAK


@dataclass
class Exchange:
    """The one command in flight: feed it lines until it returns its :class:`Reply`.

    Lines before the echo belong to nobody (a late answer to a timed-out command, an ``OK``
    banner, a config read's extra line): they go to ``stray``.
    """

    command: Command
    stray: list[str] = field(default_factory=list)
    echoed: bool = False
    _values: list[int] = field(default_factory=list)

    def feed_line(self, line: str) -> Reply | None:
        command = self.command
        if not self.echoed:
            if line == command.text:
                self.echoed = True
                if command.kind is Kind.RESET:
                    return Reply(command, Status.ECHOED)
            else:
                self.stray.append(line)
            return None
        if line == "-":
            return Reply(command, Status.NAK)
        if command.kind in (Kind.RUNTIME, Kind.CONFIG_WRITE):
            if line == "+":
                return Reply(command, Status.ACK)
            self.stray.append(line)
            return None
        if _HEX2.fullmatch(line) is None:
            self.stray.append(line)
            return None
        self._values.append(int(line, 16))
        if len(self._values) >= command.values:
            return Reply(command, Status.VALUES, tuple(self._values))
        return None
