"""A simulated Roboteq AX3500 on a pseudo-terminal, as ``../shared/hardware.md`` describes it.

:class:`Ax3500Device` is the controller itself, sans-IO: bytes in, bytes out, with the time
passed in and one deadline for its timers. It echoes every character, answers ``+``/``-``,
queries in hex, config reads and writes, ``%rrrrrr`` (a restart banner, then ``OK``), sends
``OK`` at power-up in RS-232 mode, streams ``:`` data lines in R/C mode until ten carriage
returns switch it to RS-232, and runs the watchdog (no character for more than 1 s: motors
stop, ``W`` once a second until traffic resumes). Config writes take effect at the next reset,
as on the device. Its channel outputs drive the simulated vehicle: in mixed mode channel 1 is
the common speed and channel 2 the steering.

:class:`Ax3500Simulator` serves a device on the master side of a pty (raw mode) from the
event loop (``add_reader``), pacing its output at the line's speed (9600 baud, 10 bits a
character) unless told otherwise. With ``link`` it keeps a symlink to the current pty, so
:meth:`~Ax3500Simulator.unplug` and :meth:`~Ax3500Simulator.replug` behave like a USB
adapter pulled out and put back.

Quirks the manual leaves open are options (:class:`SimOptions`): which of ``B``/``b`` turns
left, an extra line after a config read.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import tty
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field

from brasidas.actor import Supervisor
from brasidas.bus import Bus
from brasidas.clock import Cancellable, Clock, LoopClock
from brasidas.codecs import ax3500
from brasidas.config import MotorSection, PlatformConfig
from platformd.sim.owner import SimulatorOwner
from platformd.sim.vehicle import VehicleModel

_LOGGER = logging.getLogger(__name__)

CHAR_TIME_9600 = 10 / 9600
"""One character at 9600 baud with a start, 7 data, a parity and a stop bit."""
WATCHDOG_TIMEOUT = 1.0
MAX_COMMAND = 32
"""Longer input lines are answered ``-`` (no command is that long)."""


@dataclass
class SimOptions:
    """How the simulated controller behaves (the quirks the manual leaves open included)."""

    char_time: float = CHAR_TIME_9600
    """Seconds per character sent: output is paced like the real line. 0: at once."""
    left_turn: str = "B"
    """Which of "B" (channel 2 forward) or "b" turns the vehicle left."""
    extra_config_line: str | None = None
    """A line some units send after a config read's answer (e.g. "00"); None: nothing."""
    lowercase_hex: bool = False
    """Answer hex values in lowercase (drivers must accept both cases)."""
    reset_time: float = 0.3
    """Seconds from ``%rrrrrr`` to the banner and ``OK`` (the real device takes 1-2 s)."""
    banner: tuple[str, ...] = ("Roboteq v1.9b AX3500", "OK")
    """Lines sent after a reset (the last, ``OK``, is also the power-up line)."""
    rc_line_period: float = 0.1
    """In R/C or analog mode, a ``:`` data line this often."""
    parameters: dict[int, int] = field(
        default_factory=lambda: {
            ax3500.PARAM_INPUT_MODE: ax3500.INPUT_MODE_RS232_WATCHDOG,
            ax3500.PARAM_MOTOR_MODE: ax3500.MOTOR_MODE_MIXED_OPEN_LOOP,
            ax3500.PARAM_CONTROLLER_ID: 0x08,  # bit 3: AX3500
        }
    )
    """The controller's stored configuration (``^mm``), as at power-up."""
    battery_volts: float = 24.6
    """Main battery at rest; it sags a little under load."""
    internal_volts: float = 12.2
    ambient_c: float = 25.0
    """Heatsink temperature at rest; it rises with load."""
    idle_amps: float = 0.5
    full_amps: float = 20.0
    """Motor current at full power (per channel)."""


OutputCallback = Callable[[float, float], None]
"""Receives (speed, left turn), each in [-1, 1], whenever the motor outputs change."""


class Ax3500Device:
    """The controller, sans-IO: :meth:`feed` and :meth:`tick` return the bytes it sends."""

    def __init__(
        self,
        options: SimOptions | None = None,
        *,
        on_output: OutputCallback | None = None,
        record: bool = False,
    ) -> None:
        self.options = options or SimOptions()
        self.record = record
        """Keep what arrives in :attr:`received` and :attr:`received_bytes` (tests opt in: a
        ``--sim`` platform running for days keeps nothing)."""
        self.on_output = on_output
        self.parameters = dict(self.options.parameters)
        self.mode = "off"
        """"rs232", "rc" (R/C or analog: streaming data lines), "resetting" or "off"."""
        self.mixed = True
        """Motor mode in effect (read from the parameters at power-up and reset)."""
        self.watchdog = True
        self.channels = (0, 0)
        """Signed channel commands, -127..127."""
        self.outputs: dict[str, bool] = {"C": False}
        self.received: list[str] = []
        """With :attr:`record`: every command line received, in order (the last 10,000 to
        20,000)."""
        self.received_bytes = bytearray()
        """With :attr:`record`: the raw input, the last 32 to 64 KiB of it."""
        self.errors = 0
        """Commands answered ``-``."""
        self.watchdog_trips = 0
        self.w_sent = 0
        self.resets = 0
        self.fail_next = 0
        """Answer ``-`` to this many upcoming run-time commands (a flaky line, for tests)."""
        self.silent = False
        """Ignore everything and send nothing (a controller that stopped answering)."""
        self._line = bytearray()
        self._overlong = False
        self._carriage_returns = 0
        self._last_rx = 0.0
        self._tripped = False
        self._next_w = 0.0
        self._reset_done = 0.0
        self._next_data_line = 0.0

    # ------------------------------------------------------------------ power and time

    def power_up(self, now: float) -> bytes:
        """Switch on: outputs off, the stored mode in effect; ``OK`` in RS-232 mode."""
        self._set_channels(0, 0)
        self.outputs = dict.fromkeys(self.outputs, False)
        self.mixed = (
            self.parameters.get(ax3500.PARAM_MOTOR_MODE) == ax3500.MOTOR_MODE_MIXED_OPEN_LOOP
        )
        input_mode = self.parameters.get(ax3500.PARAM_INPUT_MODE, ax3500.INPUT_MODE_RC)
        self._line.clear()
        self._overlong = False
        self._carriage_returns = 0
        self._last_rx = now
        self._tripped = False
        if input_mode in (ax3500.INPUT_MODE_RS232, ax3500.INPUT_MODE_RS232_WATCHDOG):
            self.mode = "rs232"
            self.watchdog = input_mode == ax3500.INPUT_MODE_RS232_WATCHDOG
            return b"OK\r"
        self.mode = "rc"
        self._next_data_line = now + self.options.rc_line_period
        return b""

    def power_off(self) -> None:
        """No power: deaf, and the motors stop."""
        self.mode = "off"
        self._set_channels(0, 0)

    def stop_motors(self) -> None:
        """The outputs go to zero as the watchdog would make them (tests: a missed trip)."""
        self._set_channels(0, 0)

    def deadline(self) -> float | None:
        """When :meth:`tick` next has something to do."""
        if self.silent:
            return None
        if self.mode == "resetting":
            return self._reset_done
        if self.mode == "rc":
            return self._next_data_line
        if self.mode == "rs232" and self.watchdog:
            return self._next_w if self._tripped else self._last_rx + WATCHDOG_TIMEOUT
        return None

    def tick(self, now: float) -> bytes:
        """Run the timers due at ``now``: the watchdog, a reset's end, R/C data lines."""
        if self.silent:
            return b""
        if self.mode == "resetting":
            if now < self._reset_done:
                return b""
            banner = "".join(f"{line}\r" for line in self.options.banner[:-1])
            return b"\r" + banner.encode("ascii") + self.power_up(now)
        if self.mode == "rc":
            if now < self._next_data_line:
                return b""
            self._next_data_line = now + self.options.rc_line_period
            return b":0000000000000000\r"
        if self.mode != "rs232" or not self.watchdog:
            return b""
        if not self._tripped:
            if now - self._last_rx <= WATCHDOG_TIMEOUT:
                return b""
            self._tripped = True
            self.watchdog_trips += 1
            self._set_channels(0, 0)
            self._next_w = now
        if now < self._next_w:
            return b""
        self._next_w += 1.0
        self.w_sent += 1
        return b"W"

    # ------------------------------------------------------------------ input

    def feed(self, data: bytes, now: float) -> bytes:
        """Characters from the host; returns the echo and any answers."""
        if self.silent or self.mode in ("off", "resetting"):
            return b""
        self._last_rx = now
        self._tripped = False  # any character resets the watchdog
        if self.record:
            self.received_bytes += data
            if len(self.received_bytes) > 65536:
                del self.received_bytes[:-32768]
        out = bytearray()
        for byte in data:
            out += self._on_byte(byte & 0x7F, now)  # 7 data bits on the wire
            if self.mode == "resetting":
                break  # the rest of the input is lost in the restart
        return bytes(out)

    def _on_byte(self, byte: int, now: float) -> bytes:
        if self.mode == "rc":
            # Ten consecutive carriage returns switch to RS-232 (watchdog on).
            self._carriage_returns = self._carriage_returns + 1 if byte == 0x0D else 0
            if self._carriage_returns < 10:
                return b""
            self.mode, self.watchdog = "rs232", True
            self._line.clear()
            return b"OK\r"
        echo = bytes([byte])
        if byte in (0x0D, 0x0A):
            if byte == 0x0A or not (self._line or self._overlong):
                return echo
            line = self._line.decode("ascii", "replace")
            overlong = self._overlong
            self._line.clear()
            self._overlong = False
            if self.record:
                self.received.append(line)
                if len(self.received) > 20000:
                    del self.received[:10000]
            if overlong:
                self.errors += 1
                return echo + b"-\r"
            return echo + self._answer(line, now).encode("ascii")
        if len(self._line) >= MAX_COMMAND:
            self._overlong = True
        else:
            self._line.append(byte)
        return echo

    def _answer(self, line: str, now: float) -> str:
        head, body = line[:1], line[1:]
        if head == "!":
            return self._runtime(body)
        if head == "?":
            return self._query(body)
        if head == "^":
            return self._config(body)
        if line == ax3500.RESET:
            self.resets += 1
            self.mode = "resetting"
            self._reset_done = now + self.options.reset_time
            self._set_channels(0, 0)
            return ""
        return self._refuse()

    def _hex(self, value: int) -> str:
        text = f"{value & 0xFF:02X}\r"
        return text.lower() if self.options.lowercase_hex else text

    def _refuse(self) -> str:
        self.errors += 1
        return "-\r"

    def _runtime(self, body: str) -> str:
        if self.fail_next > 0:
            self.fail_next -= 1
            return self._refuse()
        if len(body) == 1 and body.upper() in self.outputs:
            self.outputs[body.upper()] = body.isupper()
            return "+\r"
        # Exactly two hex digits, 00-7F: "!a5" is refused, "!a05" is right.
        if len(body) != 3 or body[0] not in "AaBb" or not _is_hex(body[1:]):
            return self._refuse()
        value = int(body[1:], 16)
        if value > ax3500.MAX_VALUE:
            return self._refuse()
        signed = value if body[0].isupper() else -value
        one, two = self.channels
        if body[0] in "Aa":
            self._set_channels(signed, two)
        else:
            self._set_channels(one, signed)
        return "+\r"

    def _query(self, body: str) -> str:
        values = self.query_values(body) if len(body) == 1 else None
        if values is None:
            return self._refuse()
        return "".join(self._hex(value) for value in values)

    def _config(self, body: str) -> str:
        parts = body.split(" ")
        if len(parts) > 2 or not all(len(part) == 2 and _is_hex(part) for part in parts):
            return self._refuse()
        parameter = int(parts[0], 16)
        if len(parts) == 1:
            extra = self.options.extra_config_line
            answer = self._hex(self.parameters.get(parameter, 0))
            return answer + (f"{extra}\r" if extra is not None else "")
        self.parameters[parameter] = int(parts[1], 16)  # takes effect at the next reset
        return "+\r"

    # ------------------------------------------------------------------ state

    def query_values(self, letter: str) -> list[int] | None:
        """The values a ``?x`` query answers now, or None for an invalid query (``?t``)."""
        left, right = self.motor_power()
        if letter == "v":
            return [left, right]
        if letter == "a":
            return [ax3500.amps_raw(self.motor_amps(left)), ax3500.amps_raw(self.motor_amps(right))]
        if letter == "e":
            return [
                ax3500.battery_raw(self.battery_volts()),
                ax3500.internal_raw(self.options.internal_volts),
            ]
        if letter == "m":
            celsius = self.heatsink_c()
            return [ax3500.heatsink_raw(celsius), ax3500.heatsink_raw(celsius - 1.0)]
        if letter in ("p", "r"):
            return [0, 0]  # analog inputs at 2.5 V
        if letter == "i":
            return [0, 0, 1]  # inputs E and F low; emergency stop not triggered
        return None

    def motor_power(self) -> tuple[int, int]:
        """Power applied to motors 1 and 2 (00-7F, no sign)."""
        one, two = self.channels
        if not self.mixed:
            return abs(one), abs(two)
        return min(127, abs(one + two)), min(127, abs(one - two))

    def battery_volts(self) -> float:
        left, right = self.motor_power()
        return self.options.battery_volts - 0.6 * (left + right) / 254

    def motor_amps(self, power: int) -> float:
        options = self.options
        return options.idle_amps + (options.full_amps - options.idle_amps) * power / 127

    def heatsink_c(self) -> float:
        left, right = self.motor_power()
        return self.options.ambient_c + 20.0 * (left + right) / 254

    @property
    def command(self) -> tuple[float, float]:
        """What the motors do now: (speed, left turn), each in [-1, 1]."""
        one, two = self.channels
        if not self.mixed:  # separate channels: left and right motors
            return (one + two) / 254, (two - one) / 254
        turn = two if self.options.left_turn == "B" else -two
        return one / 127, turn / 127

    def _set_channels(self, one: int, two: int) -> None:
        changed = (one, two) != self.channels
        self.channels = (one, two)
        if changed and self.on_output is not None:
            self.on_output(*self.command)


def _is_hex(text: str) -> bool:
    return bool(text) and all(char in "0123456789ABCDEFabcdef" for char in text)


class Ax3500Simulator:
    """A device served on a pty: :meth:`start` on the event loop, :meth:`close` when done."""

    def __init__(
        self,
        options: SimOptions | None = None,
        *,
        vehicle: VehicleModel | None = None,
        link: str | None = None,
        clock: Clock | None = None,
        record: bool = False,
    ) -> None:
        self.device = Ax3500Device(options, on_output=self._on_output, record=record)
        self.clock: Clock = clock or LoopClock()
        """The device's time (watchdog, reset, R/C lines); the line's pacing is real time."""
        self.vehicle = vehicle
        self.link = link
        """A symlink kept pointing at the current pty (like /dev/serial/by-id), or None."""
        self.pty_name = ""
        """The current pty's slave path ("" while unplugged)."""
        self.dropped_bytes = 0
        """Output lost because nobody read the pty and its buffer was full."""
        self._loop: asyncio.AbstractEventLoop | None = None
        self._master: int | None = None
        self._slave: int | None = None
        self._pending: deque[tuple[float, bytes]] = deque()
        self._line_free_at = 0.0
        self._flush_timer: asyncio.TimerHandle | None = None
        self._device_timer: Cancellable | None = None
        self._device_deadline: float | None = None

    @property
    def path(self) -> str:
        """What a driver opens: the link if there is one, else the pty."""
        return self.link or self.pty_name

    @property
    def plugged(self) -> bool:
        return self._master is not None

    def start(self) -> None:
        """Create the pty and power the controller up. Must run on the event loop."""
        self._loop = asyncio.get_running_loop()
        self._open()

    def close(self) -> None:
        """Power off and remove the pty (and the link). Idempotent."""
        self.unplug()
        self._loop = None

    def unplug(self) -> None:
        """The adapter is pulled out: the path disappears, open handles see a hangup."""
        if self._master is None:
            return
        assert self._loop is not None
        self._loop.remove_reader(self._master)
        for handle in (self._flush_timer, self._device_timer):
            if handle is not None:
                handle.cancel()
        self._flush_timer = self._device_timer = None
        self._pending.clear()
        for fd in (self._master, self._slave):
            with contextlib.suppress(OSError):
                os.close(fd)  # type: ignore[arg-type]
        self._master = self._slave = None
        self.pty_name = ""
        if self.link is not None:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(self.link)
        self.device.power_off()

    def replug(self) -> None:
        """Plugged back in (a new pty behind the same link): a controller just powered up."""
        if self._master is None:
            self._open()

    def _open(self) -> None:
        assert self._loop is not None
        master, slave = os.openpty()
        tty.setraw(slave)  # no echo or line editing by the kernel: the device echoes
        os.set_blocking(master, False)
        # The simulator keeps the slave open too, so the master never sees a hangup (EIO)
        # while no driver has the port open.
        self._master, self._slave = master, slave
        self.pty_name = os.ttyname(slave)
        if self.link is not None:
            temporary = f"{self.link}.new"
            with contextlib.suppress(FileNotFoundError):
                os.unlink(temporary)
            os.symlink(self.pty_name, temporary)
            os.replace(temporary, self.link)
        self._line_free_at = 0.0
        self._loop.add_reader(master, self._on_readable)
        # Written at once: the controller powered up before anyone could open the port.
        self._write(self.device.power_up(self.clock.time()))
        self._schedule()

    # ------------------------------------------------------------------ I/O

    def _on_readable(self) -> None:
        assert self._loop is not None and self._master is not None
        try:
            data = os.read(self._master, 4096)
        except BlockingIOError:
            return
        except OSError:
            return  # EIO: no reader on the slave side (cannot happen while we hold it)
        self._emit(self.device.feed(data, self.clock.time()))
        self._schedule()

    def _on_device_timer(self) -> None:
        self._device_timer = None
        self._emit(self.device.tick(self.clock.time()))
        self._schedule()

    def _schedule(self) -> None:
        """Arm one timer for the device's next deadline."""
        deadline = self.device.deadline()
        if self._device_timer is not None:
            if deadline is not None and deadline == self._device_deadline:
                return
            self._device_timer.cancel()
            self._device_timer = None
        if deadline is not None:
            # A hair late, so "more than 1 s" has passed when it fires.
            self._device_deadline = deadline
            self._device_timer = self.clock.call_at(deadline + 1e-4, self._on_device_timer)

    def _emit(self, data: bytes) -> None:
        """Send ``data``, paced at the line's character time."""
        if not data or self._master is None:
            return
        assert self._loop is not None
        char_time = self.device.options.char_time
        if char_time <= 0:
            self._write(data)
            return
        now = self._loop.time()
        done = max(now, self._line_free_at) + len(data) * char_time
        self._line_free_at = done
        self._pending.append((done, data))
        if self._flush_timer is None:
            self._flush_timer = self._loop.call_at(self._pending[0][0], self._flush)

    def _flush(self) -> None:
        self._flush_timer = None
        assert self._loop is not None
        now = self._loop.time()
        while self._pending and self._pending[0][0] <= now + 1e-4:
            self._write(self._pending.popleft()[1])
        if self._pending:
            self._flush_timer = self._loop.call_at(self._pending[0][0], self._flush)

    def _write(self, data: bytes) -> None:
        if self._master is None:
            return
        try:
            written = os.write(self._master, data)
        except OSError:
            written = 0  # buffer full with nobody reading: a real line loses it too
        self.dropped_bytes += len(data) - written

    def inject(self, data: bytes) -> None:
        """Put ``data`` on the line as if the controller had sent it (noise, a stray W)."""
        self._write(data)

    def _on_output(self, speed: float, turn: float) -> None:
        if self.vehicle is not None:
            self.vehicle.set_command(speed, turn)


# --------------------------------------------------------------------------- in the platform


def options_for(motor: MotorSection) -> SimOptions:
    """A simulated controller wired like the configured chassis."""
    return SimOptions(left_turn="b" if motor.invert_angular else "B")


def start_simulator(
    bus: Bus, supervisor: Supervisor, motor: MotorSection, vehicle: VehicleModel
) -> Ax3500Simulator:
    """In ``--sim``: a simulated controller on a pty (open it 8N1: ``ctx.motor_serial``)."""
    simulator = Ax3500Simulator(options_for(motor), vehicle=vehicle)
    simulator.start()  # now: the pty exists before the driver (or a bench tap) opens it
    supervisor.start(SimulatorOwner(bus, "sim:ax3500", simulator))
    return simulator


# --------------------------------------------------------------------------- standalone


async def serve(config: PlatformConfig) -> None:
    """``brasidas-platform simulate ax3500``: print the pty path, serve until cancelled."""
    vehicle = VehicleModel()
    simulator = Ax3500Simulator(SimOptions(), vehicle=vehicle)
    simulator.start()
    try:
        print(simulator.path, flush=True)
        print(f"AX3500 simulator: 9600 baud, try: screen {simulator.path} 9600", flush=True)
        last: tuple[float, float] | None = None
        while True:
            await asyncio.sleep(1.0)
            command = simulator.device.command
            if command != last:
                last = command
                pose = vehicle.pose()
                _LOGGER.info(
                    "outputs speed %+.2f turn %+.2f; vehicle at (%.1f, %.1f) m",
                    *command,
                    pose.x_m,
                    pose.y_m,
                )
    finally:
        simulator.close()
