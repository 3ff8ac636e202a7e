"""The lights: where each is wired (a controller output or a GPIO line), their state,
switching them on request and putting them back after a controller restart."""

from __future__ import annotations

import asyncio
from collections import deque
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

from brasidas import topics
from brasidas.bus import Bus
from brasidas.codecs import ax3500
from brasidas.codecs.ax3500 import Command
from brasidas.config.platform import GPIO_PREFIX, GpioLine
from brasidas.messages import CommandResult, LightsState

if TYPE_CHECKING:
    from platformd.motor.gpio import GpioOutput, RequestLines

LIGHTS = ("main", "positional")

Send = Callable[[Command], Awaitable[bool]]
"""Sends one command on the controller's line; True when the controller acknowledged it."""


@dataclass
class OutputRequest:
    which: str
    on: bool
    reply: asyncio.Future[CommandResult]


class Lights:
    """Lights state and switching; controller outputs go out through the motor's scheduler
    (:attr:`pending`), GPIO lines through :meth:`gpio_worker`, with or without the controller."""

    def __init__(
        self, bus: Bus, outputs: Mapping[str, str], request_lines: RequestLines | None = None
    ) -> None:
        self.bus = bus
        self.outputs = {which: outputs.get(which, "").strip() for which in LIGHTS}
        """Each light's output (``C``, ``gpio:/dev/gpiochip0:17``), empty when none is fitted."""
        self.gpio: dict[str, GpioOutput] = {}
        """The lights on GPIO lines (validated with the config: parsing cannot fail here)."""
        for which, output in self.outputs.items():
            if output.startswith(GPIO_PREFIX):
                from platformd.motor.gpio import GpioOutput  # libgpiod only where it is used

                self.gpio[which] = GpioOutput(GpioLine.parse(output), request_lines)
        self.state = {"main": False, "positional": False}
        self.pending: deque[OutputRequest] = deque()
        """Requests for the controller's outputs, served between velocity commands."""
        self._gpio_requests: asyncio.Queue[OutputRequest] = asyncio.Queue()

    def output(self, which: str) -> str:
        """The output of light ``which`` (``C``, ``gpio:CHIP:LINE``), empty when none is fitted."""
        return self.outputs[which]

    def fitted(self) -> list[str]:
        return [which for which in LIGHTS if self.output(which)]

    def on_gpio(self, which: str) -> bool:
        return which in self.gpio

    def errors(self) -> dict[str, str]:
        """Why a light on a GPIO line cannot be switched (chip missing, line busy), by light."""
        return {which: output.error for which, output in self.gpio.items() if output.error}

    def request_gpio(self, request: OutputRequest) -> None:
        self._gpio_requests.put_nowait(request)

    async def gpio_worker(self) -> None:
        """Lights on GPIO lines: each requested at start (off), switched whether or not the
        controller is up, and switched off and released when the worker stops."""
        try:
            for output in self.gpio.values():
                await output.open()
            self.publish()
            while True:
                request = await self._gpio_requests.get()
                await self.serve(None, request)
        finally:
            # Off is the safe state; a cancelled stop must not leave a line held or lit.
            await asyncio.shield(self._close_gpio())

    async def _close_gpio(self) -> None:
        for which, output in self.gpio.items():
            if output.requested:
                await output.close()
                self.state[which] = False

    async def serve(self, send: Send | None, request: OutputRequest) -> None:
        ok = await self.switch(send, request.which, request.on)
        if not request.reply.done():
            state = "on" if request.on else "off"
            gpio = self.gpio.get(request.which)
            request.reply.set_result(
                CommandResult(True, result={request.which: request.on})
                if ok
                else CommandResult(
                    False,
                    f"{request.which} lights: {gpio.error}"
                    if gpio is not None
                    else f"controller did not switch the {request.which} lights {state}",
                )
            )

    async def switch(self, send: Send | None, which: str, on: bool) -> bool:
        """Switch one light; ``send`` is the controller's line (None: not connected)."""
        gpio = self.gpio.get(which)
        if gpio is not None:
            errors = self.errors()
            ok = await gpio.set(on)
            if self.errors() != errors:
                self.publish()
        elif send is None:
            return False
        else:
            ok = await send(ax3500.output(self.output(which), on))
        if ok:
            self.state[which] = on
            self.publish()
        return ok

    async def restore(self, send: Send) -> None:
        """A power-up switched the controller's outputs off: put the lights back."""
        for which in LIGHTS:
            if self.state[which] and self.output(which) and not self.on_gpio(which):
                await self.switch(send, which, True)

    def fail_pending(self, reason: str) -> None:
        """Answer every request not served yet (the actor stops)."""
        for request in (*self.pending, *_drain(self._gpio_requests)):
            if not request.reply.done():
                request.reply.set_result(CommandResult(False, reason))
        self.pending.clear()

    def publish(self) -> None:
        self.bus.publish(
            topics.LIGHTS_STATE,
            LightsState(self.state["main"], self.state["positional"], self.errors()),
        )


def _drain(queue: asyncio.Queue[OutputRequest]) -> list[OutputRequest]:
    items = []
    while not queue.empty():
        items.append(queue.get_nowait())
    return items
