"""GPIO outputs through libgpiod v2 (``gpiod``, the character device; never sysfs).

An output is ``gpio:CHIP:LINE`` in the config: ``CHIP`` a character device (``/dev/gpiochip0``,
or ``gpiochip0`` for it), ``LINE`` an offset (``17``) or a line name (``GPIO17``). The line is
requested once, as an output driven low (off), and kept until :meth:`GpioOutput.close`,
which drives it low again and releases it. Every libgpiod call runs in a worker thread (the
lights' GPIO worker awaits them one at a time), never on the event loop. A chip that does not
exist, a line another process holds or an unknown line name is :attr:`GpioOutput.error`
(the request is tried again at the next switch), never an exception.
"""

from __future__ import annotations

import asyncio
import errno
import logging
from collections.abc import Callable
from typing import Protocol

import gpiod
from gpiod.line import Direction, Value

from brasidas.config.platform import GpioLine

_LOGGER = logging.getLogger(__name__)

CONSUMER = "brasidas-platform"
"""The consumer name the kernel shows for our lines (``gpioinfo``)."""


class LineRequest(Protocol):
    """What we use of ``gpiod.LineRequest``."""

    def set_value(self, line: int | str, value: Value) -> None: ...

    def release(self) -> None: ...


RequestLines = Callable[..., LineRequest]
"""``gpiod.request_lines`` (or a simulated chip's, with the same signature)."""


class GpioOutput:
    """One output line: requested on first use, switched, driven low and released on close.

    Its methods are awaited from one task at a time (the lights' GPIO worker)."""

    def __init__(self, line: GpioLine, request_lines: RequestLines | None = None) -> None:
        self.line = line
        self.request_lines: RequestLines = request_lines or gpiod.request_lines
        self.error = ""
        """Why the line cannot be switched (chip missing, line busy); empty when it can."""
        self._request: LineRequest | None = None

    @property
    def requested(self) -> bool:
        return self._request is not None

    async def open(self) -> bool:
        """Request the line (driven low) unless held already; False with :attr:`error`."""
        if self._request is None:
            try:
                self._request = await asyncio.to_thread(self._request_line)
            except (OSError, ValueError) as err:
                self._set_error(f"cannot request GPIO line {self.line}: {_describe(err)}")
                return False
            _LOGGER.info("GPIO line %s requested", self.line)
        self.error = ""
        return True

    async def set(self, on: bool) -> bool:
        """Drive the line high (on) or low; False with :attr:`error` when it cannot."""
        if not await self.open():
            return False
        request = self._request
        assert request is not None
        try:
            await asyncio.to_thread(request.set_value, self.line.line, _value(on))
        except (OSError, ValueError, gpiod.RequestReleasedError) as err:
            self._set_error(f"cannot switch GPIO line {self.line}: {_describe(err)}")
            return False
        return True

    async def close(self) -> None:
        """Drive the line low (off: the safe state) and release it; idempotent."""
        request, self._request = self._request, None
        if request is not None:
            await asyncio.to_thread(_off_and_release, request, self.line)

    def _request_line(self) -> LineRequest:
        """Worker thread."""
        settings = gpiod.LineSettings(direction=Direction.OUTPUT, output_value=Value.INACTIVE)
        return self.request_lines(
            self.line.chip, config={self.line.line: settings}, consumer=CONSUMER
        )

    def _set_error(self, error: str) -> None:
        if error != self.error:
            _LOGGER.warning("%s", error)
        self.error = error


def _value(on: bool) -> Value:
    return Value.ACTIVE if on else Value.INACTIVE


def _off_and_release(request: LineRequest, line: GpioLine) -> None:
    """Worker thread."""
    try:
        request.set_value(line.line, Value.INACTIVE)
    except (OSError, ValueError, gpiod.RequestReleasedError) as err:
        _LOGGER.warning("GPIO line %s not switched off: %s", line, _describe(err))
    finally:
        request.release()


def _describe(err: Exception) -> str:
    if isinstance(err, OSError) and err.strerror:
        hint = _HINTS.get(err.errno or 0, "")
        return f"{hint} ({err.strerror})" if hint else err.strerror
    return str(err) or type(err).__name__


_HINTS = {
    errno.ENOENT: "no such GPIO chip",
    errno.EBUSY: "line busy, held by another consumer",
    errno.EACCES: "permission denied (the gpio group?)",
    errno.ENOTTY: "not a GPIO character device",
    errno.ENODEV: "not a GPIO character device",
}
