"""Simulated GPIO chips for ``--sim`` and tests: libgpiod v2's request API over a dict.

No gpiochip, gpio-sim or configfs exists on a build machine, so the GPIO outputs' driver
(:mod:`platformd.motor.gpio`) is pointed at :meth:`SimulatedGpio.request_lines` instead of
``gpiod.request_lines``: the same signature, answering with a :class:`SimulatedLineRequest`
that has ``gpiod.LineRequest``'s methods and raises what libgpiod raises (``FileNotFoundError``
for a missing chip, ``OSError(EBUSY)`` for a line held by another consumer, ``ValueError`` for
an unknown line name or an offset past the chip's lines, ``RequestReleasedError`` after release).
Values are ``gpiod.line.Value``, settings ``gpiod.LineSettings``.
"""

from __future__ import annotations

import errno
import os
import threading
from collections.abc import Iterable
from dataclasses import dataclass, field

import gpiod
from gpiod.line import Direction, Value

SIM_CHIP = "/dev/gpiochip0"
SIM_LIGHTS_OUTPUT = f"gpio:{SIM_CHIP}:17"
"""Where the simulated positional lights hang when ``motor.positional_lights_output`` is empty."""


@dataclass
class SimulatedLine:
    value: Value = Value.INACTIVE
    direction: Direction = Direction.INPUT
    consumer: str | None = None
    """Who holds the line; None: free."""


@dataclass
class SimulatedChip:
    path: str
    num_lines: int = 54
    """A Raspberry Pi's first chip has 54 lines, named GPIO0..GPIO53."""
    lines: dict[int, SimulatedLine] = field(default_factory=dict)

    def line(self, offset: int) -> SimulatedLine:
        return self.lines.setdefault(offset, SimulatedLine())

    def offset(self, line: int | str) -> int:
        if isinstance(line, int):
            if not 0 <= line < self.num_lines:
                raise ValueError(f"offset {line} out of range (chip has {self.num_lines} lines)")
            return line
        if line.startswith("GPIO") and line[4:].isdecimal() and int(line[4:]) < self.num_lines:
            return int(line[4:])
        raise ValueError(f"unable to map line '{line}' to offset")


class SimulatedGpio:
    """The simulated chips; :meth:`request_lines` stands in for ``gpiod.request_lines``."""

    def __init__(self, chips: Iterable[str] = (SIM_CHIP,)) -> None:
        self.chips = {path: SimulatedChip(path) for path in chips}
        self.calls: list[tuple[str, int]] = []
        """Each call into the chips: its name and the calling thread's id."""
        self._lock = threading.Lock()

    def value(self, chip: str, offset: int) -> Value:
        return self.chips[chip].line(offset).value

    def holder(self, chip: str, offset: int) -> str | None:
        """The consumer holding the line, None when free."""
        return self.chips[chip].line(offset).consumer

    def request_lines(
        self,
        path: str,
        config: dict[Iterable[int | str] | int | str, gpiod.LineSettings | None],
        consumer: str | None = None,
        event_buffer_size: int | None = None,
        output_values: dict[int | str, Value] | None = None,
    ) -> SimulatedLineRequest:
        """``gpiod.request_lines``: the lines of ``config`` for ``consumer``, or its errors."""
        with self._lock:
            self.calls.append(("request_lines", threading.get_ident()))
            chip = self.chips.get(os.path.realpath(path)) or self.chips.get(path)
            if chip is None:
                raise FileNotFoundError(errno.ENOENT, os.strerror(errno.ENOENT), path)
            wanted: dict[int, tuple[int | str, gpiod.LineSettings]] = {}
            for key, settings in config.items():
                for line in (key,) if isinstance(key, int | str) else key:
                    wanted[chip.offset(line)] = (line, settings or gpiod.LineSettings())
            if any(chip.line(offset).consumer is not None for offset in wanted):
                raise OSError(errno.EBUSY, os.strerror(errno.EBUSY))
            for offset, (line, settings) in wanted.items():
                state = chip.line(offset)
                state.consumer = consumer or "?"
                state.direction = settings.direction
                if settings.direction is Direction.OUTPUT:
                    state.value = (output_values or {}).get(line, settings.output_value)
            names = {line: offset for offset, (line, _) in wanted.items() if isinstance(line, str)}
            return SimulatedLineRequest(self, chip, list(wanted), names)


class SimulatedLineRequest:
    """``gpiod.LineRequest`` over a simulated chip (the methods a GPIO output uses, and reads)."""

    def __init__(
        self, gpio: SimulatedGpio, chip: SimulatedChip, offsets: list[int], names: dict[str, int]
    ) -> None:
        self._gpio = gpio
        self._chip: SimulatedChip | None = chip
        self._offsets = offsets
        self._names = names

    def __bool__(self) -> bool:
        return self._chip is not None

    @property
    def chip_name(self) -> str:
        return os.path.basename(self._live().path)

    @property
    def offsets(self) -> list[int]:
        self._live()
        return list(self._offsets)

    @property
    def num_lines(self) -> int:
        return len(self.offsets)

    def release(self) -> None:
        with self._gpio._lock:
            self._gpio.calls.append(("release", threading.get_ident()))
            if self._chip is not None:
                for offset in self._offsets:
                    self._chip.line(offset).consumer = None
                self._chip = None

    def get_value(self, line: int | str) -> Value:
        return self.get_values([line])[0]

    def get_values(self, lines: Iterable[int | str] | None = None) -> list[Value]:
        chip = self._live()
        offsets = [self._offset(line) for line in (lines or self._offsets)]
        return [chip.line(offset).value for offset in offsets]

    def set_value(self, line: int | str, value: Value) -> None:
        self.set_values({line: value})

    def set_values(self, values: dict[int | str, Value]) -> None:
        with self._gpio._lock:
            self._gpio.calls.append(("set_values", threading.get_ident()))
            chip = self._live()
            for line, value in values.items():
                if not isinstance(value, Value):
                    raise TypeError(f"expected gpiod.line.Value, not {value!r}")
                state = chip.line(self._offset(line))
                if state.direction is not Direction.OUTPUT:
                    raise OSError(errno.EPERM, os.strerror(errno.EPERM))
                state.value = value

    def _live(self) -> SimulatedChip:
        if self._chip is None:
            raise gpiod.RequestReleasedError()
        return self._chip

    def _offset(self, line: int | str) -> int:
        if isinstance(line, int):
            if line not in self._offsets:
                raise ValueError(f"line {line} not requested")
            return line
        if line not in self._names:
            raise ValueError(f"unknown line name: {line}")
        return self._names[line]
