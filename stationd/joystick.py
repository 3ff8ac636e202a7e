"""Game controller input through the Linux joystick interface (``/dev/input/jsN``).

The kernel hands out 8-byte ``js_event`` records: ``u32 time (ms), s16 value, u8 type,
u8 number``; type 1 is a button, 2 an axis, with 0x80 set on the synthetic events that
report the initial state right after ``open``. :class:`JsEventDecoder` is the sans-IO codec,
:class:`Gamepad` the controller's state, :func:`gamepad_velocity` the teleop mapping (an
enable button that must be held, deadzone, scaling, inversion) and :class:`JoystickReader`
the actor that reads the device without blocking and survives unplugging.

Layout: a Logitech F310 in XInput mode and an Xbox pad both report axes 0/1 left stick
X/Y, 2 LT, 3/4 right stick X/Y, 5 RT, 6/7 d-pad; buttons 0 A, 1 B, 2 X, 3 Y, 4 LB, 5 RB,
6 Back, 7 Start, 8 Guide, 9/10 stick clicks. Sticks read negative up and left.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import os
import struct
from dataclasses import dataclass

from brasidas.actor import Actor
from brasidas.backoff import Backoff
from brasidas.bus import Bus
from brasidas.config import JoystickSection
from brasidas.messages import Velocity

_LOGGER = logging.getLogger(__name__)

JS_EVENT = struct.Struct("=IhBB")
JS_EVENT_BUTTON = 0x01
JS_EVENT_AXIS = 0x02
JS_EVENT_INIT = 0x80
AXIS_MAX = 32767

# F310 (XInput) / Xbox button and axis numbers, for configuration and tests.
BUTTON_A, BUTTON_B, BUTTON_X, BUTTON_Y, BUTTON_LB, BUTTON_RB = range(6)
AXIS_LEFT_X, AXIS_LEFT_Y, AXIS_LT, AXIS_RIGHT_X, AXIS_RIGHT_Y, AXIS_RT = range(6)


@dataclass(frozen=True)
class JsEvent:
    time_ms: int
    value: int
    type: int
    number: int

    @property
    def kind(self) -> int:
        """``JS_EVENT_BUTTON`` or ``JS_EVENT_AXIS`` (the init flag masked off)."""
        return self.type & ~JS_EVENT_INIT

    def encode(self) -> bytes:
        return JS_EVENT.pack(self.time_ms, self.value, self.type, self.number)


class JsEventDecoder:
    """Bytes from the device to events; keeps a partial record until the rest arrives."""

    def __init__(self) -> None:
        self._buffer = b""
        self.unknown = 0
        """Records of a type other than button or axis (counted, skipped)."""

    def feed(self, data: bytes) -> list[JsEvent]:
        buffer = self._buffer + data
        whole = len(buffer) - len(buffer) % JS_EVENT.size
        self._buffer = buffer[whole:]
        events = []
        for time_ms, value, kind, number in JS_EVENT.iter_unpack(buffer[:whole]):
            event = JsEvent(time_ms, value, kind, number)
            if event.kind in (JS_EVENT_BUTTON, JS_EVENT_AXIS):
                events.append(event)
            else:
                self.unknown += 1
        return events

    def reset(self) -> None:
        self._buffer = b""


class Gamepad:
    """The controller's current axes and buttons."""

    def __init__(self) -> None:
        self.axes: dict[int, int] = {}
        self.buttons: dict[int, bool] = {}

    def apply(self, event: JsEvent) -> None:
        if event.kind == JS_EVENT_AXIS:
            self.axes[event.number] = event.value
        elif event.kind == JS_EVENT_BUTTON:
            self.buttons[event.number] = event.value != 0

    def axis(self, number: int) -> float:
        """Axis ``number`` in [-1, 1]; 0 when never reported."""
        return max(-1.0, min(1.0, self.axes.get(number, 0) / AXIS_MAX))

    def pressed(self, number: int) -> bool:
        return self.buttons.get(number, False)

    def reset(self) -> None:
        """Forget everything: an unplugged controller holds no button and no stick."""
        self.axes.clear()
        self.buttons.clear()


def shape(value: float, deadzone: float) -> float:
    """Zero inside the deadzone, then rising linearly from 0 to ±1 (no jump at its edge)."""
    magnitude = abs(value)
    if magnitude <= deadzone or deadzone >= 1.0:
        return 0.0
    scaled = min(1.0, (magnitude - deadzone) / (1.0 - deadzone))
    return scaled if value > 0 else -scaled


def gamepad_velocity(pad: Gamepad, config: JoystickSection) -> Velocity | None:
    """The commanded velocity, or None when the enable button is not held."""
    if not pad.pressed(config.enable_button):
        return None
    linear = shape(pad.axis(config.linear_axis), config.deadzone) * config.linear_scale
    angular = shape(pad.axis(config.angular_axis), config.deadzone) * config.angular_scale
    if config.invert_linear:
        linear = -linear
    if config.invert_angular:
        angular = -angular
    return Velocity(max(-1.0, min(1.0, linear)) + 0.0, max(-1.0, min(1.0, angular)) + 0.0)


class JoystickReader(Actor):
    """Reads ``config.device`` without blocking; reopens it with backoff when it goes away."""

    name = "joystick"

    def __init__(self, bus: Bus, config: JoystickSection) -> None:
        super().__init__(bus)
        self.config = config
        self.pad = Gamepad()
        self.decoder = JsEventDecoder()
        self.connected = asyncio.Event()
        self.events = 0
        self.disconnects = 0

    def velocity(self) -> Velocity | None:
        """What the controller commands now; None when not connected or enable not held."""
        if not self.connected.is_set():
            return None
        return gamepad_velocity(self.pad, self.config)

    async def run(self) -> None:
        backoff = Backoff(0.2, 2.0)
        reported = False
        loop = asyncio.get_running_loop()
        while True:
            try:
                fd = os.open(self.config.device, os.O_RDONLY | os.O_NONBLOCK | os.O_NOCTTY)
            except OSError as err:
                if not reported:
                    _LOGGER.warning("joystick %s: %s; retrying", self.config.device, err.strerror)
                    reported = True
                await asyncio.sleep(backoff.next())
                continue
            _LOGGER.info("joystick %s open", self.config.device)
            reported = False
            opened = loop.time()
            lost: asyncio.Future[str] = loop.create_future()
            loop.add_reader(fd, self._on_readable, fd, lost)
            self.connected.set()
            try:
                reason = await lost
            finally:
                loop.remove_reader(fd)
                os.close(fd)
                self.connected.clear()
                self.pad.reset()
                self.decoder.reset()
            self.disconnects += 1
            _LOGGER.warning("joystick %s lost (%s)", self.config.device, reason)
            # A device that opens and fails at once must not become a busy loop.
            if loop.time() - opened > 5.0:
                backoff.reset()
            await asyncio.sleep(backoff.next())

    def _on_readable(self, fd: int, lost: asyncio.Future[str]) -> None:
        try:
            data = os.read(fd, JS_EVENT.size * 64)
        except BlockingIOError:
            return
        except OSError as err:
            if not lost.done():
                lost.set_result(errno.errorcode.get(err.errno or 0, str(err)))
            return
        if not data:
            if not lost.done():
                lost.set_result("end of file")
            return
        for event in self.decoder.feed(data):
            self.pad.apply(event)
            self.events += 1
