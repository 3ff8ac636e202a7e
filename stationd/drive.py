"""``brasidas-station drive ID``: drive a platform from the keyboard.

Takes over the terminal (raw mode): arrows or WASD step the linear and angular command, space
stops, q (or Ctrl-C) stops, releases the manual override and quits. The command goes to the
running station daemon (``teleop_set``, repeated every 100 ms so it never goes stale) whose
sender streams it as ``$PVEL``; the status line shows what is commanded, what the daemon
streams, and what the platform reports back (mode, motor command, deadman, link counters).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import os
import sys
import termios
import tty
from collections.abc import Iterator
from enum import Enum
from typing import Any, TextIO

from brasidas.codecs.jsonrpc import RpcError
from brasidas.config import StationConfig
from brasidas.rpc import RpcClient
from stationd.api_client import CliError

SEND_INTERVAL = 0.1
"""How often the command is repeated to the daemon (its drive timeout is 0.5 s)."""
STATUS_INTERVAL = 0.5
"""How often the platform's own report is fetched for the status line."""


class Key(Enum):
    FORWARD = "forward"
    BACK = "back"
    LEFT = "left"
    RIGHT = "right"
    STOP = "stop"
    QUIT = "quit"


_ESCAPES: dict[bytes, Key] = {
    b"\x1b[A": Key.FORWARD,
    b"\x1b[B": Key.BACK,
    b"\x1b[C": Key.RIGHT,
    b"\x1b[D": Key.LEFT,
    b"\x1bOA": Key.FORWARD,  # application cursor mode
    b"\x1bOB": Key.BACK,
    b"\x1bOC": Key.RIGHT,
    b"\x1bOD": Key.LEFT,
}
_KEYS: dict[int, Key] = {
    ord("w"): Key.FORWARD,
    ord("s"): Key.BACK,
    ord("a"): Key.LEFT,
    ord("d"): Key.RIGHT,
    ord(" "): Key.STOP,
    ord("q"): Key.QUIT,
    0x03: Key.QUIT,  # Ctrl-C arrives as a byte in raw mode
    0x04: Key.QUIT,  # Ctrl-D
}


class KeyDecoder:
    """Terminal input bytes to keys (sans-IO); an escape sequence may arrive in pieces."""

    def __init__(self) -> None:
        self._buffer = b""

    def feed(self, data: bytes) -> list[Key]:
        buffer = self._buffer + data
        keys: list[Key] = []
        i = 0
        while i < len(buffer):
            if buffer[i] == 0x1B:
                sequence = buffer[i : i + 3]
                if len(sequence) < 3 and any(e.startswith(sequence) for e in _ESCAPES):
                    break  # wait for the rest
                key = _ESCAPES.get(sequence)
                if key is not None:
                    keys.append(key)
                    i += 3
                else:
                    i += 1  # a lone ESC or a sequence we do not use
                continue
            key = _KEYS.get(buffer[i] | 0x20 if 0x41 <= buffer[i] <= 0x5A else buffer[i])
            if key is not None:
                keys.append(key)
            i += 1
        self._buffer = buffer[i:]
        return keys


class DriveCommand:
    """The keyboard's velocity: each key steps it by ``step``, within [-1, 1]."""

    def __init__(self, step: float = 0.1) -> None:
        self.step = step
        self.linear = 0.0
        self.angular = 0.0

    def apply(self, key: Key) -> None:
        if key is Key.FORWARD:
            self.linear += self.step
        elif key is Key.BACK:
            self.linear -= self.step
        elif key is Key.LEFT:
            self.angular += self.step  # positive angular z turns left
        elif key is Key.RIGHT:
            self.angular -= self.step
        elif key in (Key.STOP, Key.QUIT):
            self.linear = self.angular = 0.0
        self.linear = round(max(-1.0, min(1.0, self.linear)), 3) + 0.0
        self.angular = round(max(-1.0, min(1.0, self.angular)), 3) + 0.0


@contextlib.contextmanager
def raw_terminal(fd: int) -> Iterator[None]:
    """Raw mode for the duration; the terminal is restored however we leave."""
    saved = termios.tcgetattr(fd)
    try:
        tty.setraw(fd)
        yield
    finally:
        termios.tcsetattr(fd, termios.TCSAFLUSH, saved)


def status_line(
    platform_id: str,
    command: DriveCommand,
    local: dict[str, Any] | None,
    remote: dict[str, Any] | None,
) -> str:
    parts = [f"{platform_id}  command {command.linear:+.2f} {command.angular:+.2f}"]
    if local is not None:
        parts.append(
            f"streaming {local['linear']:+.2f} {local['angular']:+.2f} #{local['sent']}"
            if local.get("streaming")
            else "not streaming"
        )
    platform = (remote or {}).get("platform") or {}
    motion = platform.get("motion") or {}
    if motion:
        link = platform.get("velocity_link") or {}
        dropped = sum((link.get("dropped") or {}).values())
        parts.append(
            f"platform {motion.get('mode', '?')} motors {motion['linear']:+.2f} "
            f"{motion['angular']:+.2f}{' DEADMAN' if motion.get('deadman') else ''} "
            f"ok {link.get('accepted', 0)} dropped {dropped}"
        )
    return " | ".join(parts)


class DriveSession:
    """The interactive loop: keys in, ``teleop_set`` out, the status line redrawn."""

    def __init__(
        self, client: RpcClient, platform_id: str, step: float, fd: int, out: TextIO
    ) -> None:
        self.client = client
        self.platform_id = platform_id
        self.command = DriveCommand(step)
        self.decoder = KeyDecoder()
        self.fd = fd
        self.out = out
        self.local: dict[str, Any] | None = None
        self.remote: dict[str, Any] | None = None
        self.quit = asyncio.Event()
        self.changed = asyncio.Event()
        self.error = ""
        """Why the session ended early (the platform or the daemon went away)."""

    def on_input(self) -> None:
        try:
            data = os.read(self.fd, 64)
        except BlockingIOError:
            return
        except OSError:
            data = b""
        if not data:
            self.quit.set()  # the terminal went away
            return
        for key in self.decoder.feed(data):
            self.command.apply(key)
            if key is Key.QUIT:
                self.quit.set()
        self.changed.set()

    async def run(self) -> None:
        loop = asyncio.get_running_loop()
        loop.add_reader(self.fd, self.on_input)
        try:
            async with asyncio.TaskGroup() as group:
                status = group.create_task(self._poll_status(), name="drive-status")
                await self._send_loop()
                status.cancel("quitting")
        finally:
            loop.remove_reader(self.fd)

    async def _send_loop(self) -> None:
        while not self.quit.is_set():
            self.changed.clear()
            params = {
                "platform_id": self.platform_id,
                "linear": self.command.linear,
                "angular": self.command.angular,
            }
            try:
                self.local = await self.client.call("teleop_set", params)
            except (RpcError, ConnectionError) as err:
                self._fail(err)
                return
            self.render()
            # asyncio.timeout: 3.11's wait_for swallows a cancellation that comes as the
            # event is set, and this loop would go on.
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(SEND_INTERVAL):
                    await self.changed.wait()

    async def _poll_status(self) -> None:
        while not self.quit.is_set():
            try:
                self.remote = await self.client.call(
                    "teleop_status", {"platform_id": self.platform_id}
                )
            except (RpcError, ConnectionError) as err:
                self._fail(err)
                return
            self.render()
            await asyncio.sleep(STATUS_INTERVAL)

    def _fail(self, err: Exception) -> None:
        if not self.error:
            self.error = err.message if isinstance(err, RpcError) else str(err)
        self.quit.set()
        self.changed.set()

    def render(self) -> None:
        line = status_line(self.platform_id, self.command, self.local, self.remote)
        self.out.write("\r\x1b[K" + line)
        self.out.flush()


async def drive(
    config: StationConfig,
    platform_id: str,
    *,
    url: str = "",
    step: float = 0.1,
    fd: int | None = None,
    out: TextIO | None = None,
) -> int:
    """Engage, drive until q, then stop and release the override. Returns the exit code."""
    fd = sys.stdin.fileno() if fd is None else fd
    out = out or sys.stdout
    if not os.isatty(fd):
        raise CliError("drive needs a terminal (it reads single keys)")
    station = config.station
    client = RpcClient(
        f"ws://{station.api_host}:{station.api_port}/api/rpc/ws",
        timeout=station.connect_timeout * 2 + 2,
    )
    try:
        await client.open()
    except OSError:
        raise CliError(
            f"the station daemon is not running at {client.url} "
            "(start it with 'brasidas-station serve')"
        ) from None
    engaged = False
    try:
        if url:
            await client.call("connect", {"platform_id": platform_id, "url": url})
        answer = await client.call("movrd", {"platform_id": platform_id, "engaged": True})
        if not answer.get("accepted"):
            raise CliError(f"manual override refused: {answer.get('reason') or 'no reason'}")
        engaged = True
        out.write(
            f"driving {platform_id}: arrows/WASD steer, space stops, "
            "q stops, releases the override and quits\n"
        )
        session = DriveSession(client, platform_id, step, fd, out)
        with raw_terminal(fd):
            try:
                await session.run()
            finally:
                out.write("\r\n")
                out.flush()
        if session.error:
            raise CliError(f"driving {platform_id} stopped: {session.error}")
    finally:
        if engaged:
            with contextlib.suppress(RpcError, ConnectionError, OSError):
                await client.call(
                    "teleop_set",
                    {"platform_id": platform_id, "linear": 0.0, "angular": 0.0},
                    timeout=1.0,
                )
            with contextlib.suppress(RpcError, ConnectionError, OSError):
                answer = await client.call(
                    "movrd", {"platform_id": platform_id, "engaged": False}, timeout=2.0
                )
                out.write(
                    "override released\n"
                    if answer.get("accepted")
                    else f"override NOT released: {answer.get('reason')}\n"
                )
        await client.close()
    return 0


def run_drive(args: argparse.Namespace, config: StationConfig) -> int:
    return asyncio.run(drive(config, args.id, url=args.url or "", step=args.step))
