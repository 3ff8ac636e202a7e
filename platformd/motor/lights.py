"""The lights: where each is wired (a controller output or a GPIO value file), their state,
switching them on request and putting them back after a controller restart."""

from __future__ import annotations

import asyncio
import logging
from collections import deque
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from brasidas import topics
from brasidas.bus import Bus
from brasidas.codecs import ax3500
from brasidas.codecs.ax3500 import Command
from brasidas.messages import CommandResult, LightsState

_LOGGER = logging.getLogger(__name__)

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

    def __init__(self, bus: Bus, outputs: Mapping[str, str]) -> None:
        self.bus = bus
        self.outputs = {which: outputs.get(which, "").strip() for which in LIGHTS}
        """Each light's output (``C``, ``gpio:/path``), empty when none is fitted."""
        self.state = {"main": False, "positional": False}
        self.pending: deque[OutputRequest] = deque()
        """Requests for the controller's outputs, served between velocity commands."""
        self._gpio_requests: asyncio.Queue[OutputRequest] = asyncio.Queue()

    def output(self, which: str) -> str:
        """The output of light ``which`` (``C``, ``gpio:/path``), empty when none is fitted."""
        return self.outputs[which]

    def fitted(self) -> list[str]:
        return [which for which in LIGHTS if self.output(which)]

    def on_gpio(self, which: str) -> bool:
        return self.output(which).startswith("gpio:")

    def request_gpio(self, request: OutputRequest) -> None:
        self._gpio_requests.put_nowait(request)

    async def gpio_worker(self) -> None:
        """Lights wired to GPIO value files: switched whether or not the controller is up."""
        while True:
            request = await self._gpio_requests.get()
            await self.serve(None, request)

    async def serve(self, send: Send | None, request: OutputRequest) -> None:
        ok = await self.switch(send, request.which, request.on)
        if not request.reply.done():
            state = "on" if request.on else "off"
            request.reply.set_result(
                CommandResult(True, result={request.which: request.on})
                if ok
                else CommandResult(
                    False, f"controller did not switch the {request.which} lights {state}"
                )
            )

    async def switch(self, send: Send | None, which: str, on: bool) -> bool:
        """Switch one light; ``send`` is the controller's line (None: not connected)."""
        output = self.output(which)
        if output.startswith("gpio:"):
            ok = await _write_gpio(output.removeprefix("gpio:"), on)
        elif send is None:
            return False
        else:
            ok = await send(ax3500.output(output, on))
        if ok:
            self.state[which] = on
            self.publish()
        return ok

    async def restore(self, send: Send) -> None:
        """A power-up switched the controller's outputs off: put the lights back."""
        for which in LIGHTS:
            output = self.output(which)
            if self.state[which] and output and not output.startswith("gpio:"):
                await self.switch(send, which, True)

    def fail_pending(self, reason: str) -> None:
        """Answer every request not served yet (the actor stops)."""
        for request in (*self.pending, *_drain(self._gpio_requests)):
            if not request.reply.done():
                request.reply.set_result(CommandResult(False, reason))
        self.pending.clear()

    def publish(self) -> None:
        self.bus.publish(
            topics.LIGHTS_STATE, LightsState(self.state["main"], self.state["positional"])
        )


async def _write_gpio(path: str, on: bool) -> bool:
    try:
        await asyncio.to_thread(Path(path).write_text, "1\n" if on else "0\n")
    except OSError as err:
        _LOGGER.warning("cannot switch %s: %s", path, err)
        return False
    return True


def _drain(queue: asyncio.Queue[OutputRequest]) -> list[OutputRequest]:
    items = []
    while not queue.empty():
        items.append(queue.get_nowait())
    return items
