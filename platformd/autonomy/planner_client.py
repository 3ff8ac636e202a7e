"""The patrol's planner process, seen from the platform (:mod:`brasidas.autonomy.planner_worker`).

The patrol actor owns it: :meth:`PlannerProcess.run` starts the process, sends it the latest
map and hands each answer to ``on_answer``; when the process dies it says so
(``on_lost``) and starts another after a backoff, which gets the latest map again. Cancelling
``run`` kills the process and waits for it (the daemon's stop leaves no process behind).
Everything here is asyncio on a Unix socket: nothing blocks the event loop, and the
process's NumPy and Shapely never hold this process's GIL.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
import socket
import sys
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import orjson

from brasidas.autonomy.planner_worker import HEADER, frame, parse_header
from brasidas.backoff import Backoff
from brasidas.states import Transitions

_LOGGER = logging.getLogger(__name__)
KILL_WAIT_S = 0.8
"""How long a stop waits for the killed process to be reaped."""


class PlannerState(enum.Enum):
    IDLE = "idle"
    """Not started yet."""
    STARTING = "starting"
    """The process is being started and connected."""
    RUNNING = "running"
    """Connected: maps and plans go to it."""
    LOST = "lost"
    """It died (or could not start): another starts after the backoff."""
    CLOSED = "closed"
    """``run`` was cancelled: the process is killed and reaped."""


PLANNER_TRANSITIONS = Transitions[PlannerState](
    "planner process",
    {
        PlannerState.IDLE: frozenset((PlannerState.STARTING, PlannerState.CLOSED)),
        PlannerState.STARTING: frozenset(
            (PlannerState.RUNNING, PlannerState.LOST, PlannerState.CLOSED)
        ),
        PlannerState.RUNNING: frozenset((PlannerState.LOST, PlannerState.CLOSED)),
        PlannerState.LOST: frozenset((PlannerState.STARTING, PlannerState.CLOSED)),
        # The patrol actor restarted by its supervisor runs it again.
        PlannerState.CLOSED: frozenset((PlannerState.STARTING,)),
    },
)


@dataclass(frozen=True)
class MapRevision:
    revision: int
    geojson: bytes
    clearance: float


class PlannerProcess:
    def __init__(
        self,
        on_answer: Callable[[dict[str, Any]], None],
        on_lost: Callable[[str], None],
        *,
        backoff_initial: float = 0.2,
        backoff_max: float = 5.0,
    ) -> None:
        self._on_answer = on_answer
        self._on_lost = on_lost
        self._backoff = Backoff(backoff_initial, backoff_max)
        self._map: MapRevision | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._resent: int | None = None
        self.pid: int | None = None
        """The running process's id (None while there is none)."""
        self.restarts = 0
        """Processes started after the first (each one after a death)."""
        self.state = PlannerState.IDLE

    def _to(self, state: PlannerState) -> None:
        self.state = PLANNER_TRANSITIONS.check(self.state, state)

    def set_map(self, revision: int, geojson: bytes, clearance: float) -> None:
        """The map the graph is for from now on (sent at once when the process runs)."""
        self._map = MapRevision(revision, geojson, clearance)
        self._send({"op": "map", "revision": revision, "clearance": clearance}, geojson)

    def edit_map(
        self, revision: int, base: int, changes: bytes, geojson: bytes, clearance: float
    ) -> None:
        """Keep-outs changed (``changes``: ``{"add": [...], "remove": [...]}`` as JSON) on map
        ``base``; ``geojson`` is the whole map, sent instead if the process asks for it."""
        self._map = MapRevision(revision, geojson, clearance)
        header = {"op": "edit", "revision": revision, "base": base, "clearance": clearance}
        self._send(header, changes)

    def resend(self, revision: int) -> None:
        """The process has not the map an edit changes (or failed on one): the whole of the
        latest map, once per revision."""
        latest = self._map
        if latest is None or latest.revision != revision or self._resent == revision:
            return
        self._resent = revision
        header = {"op": "map", "revision": latest.revision, "clearance": latest.clearance}
        self._send(header, latest.geojson)

    def request_plan(
        self, revision: int, request: int, start: tuple[float, float], goal: tuple[float, float]
    ) -> bool:
        """Ask for a path (the answer comes to ``on_answer``); False when no process runs."""
        return self._send(
            {
                "op": "plan",
                "revision": revision,
                "id": request,
                "start": list(start),
                "goal": list(goal),
            }
        )

    def _send(self, header: dict[str, Any], body: bytes = b"") -> bool:
        writer = self._writer
        if writer is None or writer.is_closing():
            return False
        writer.write(frame(header, body))  # buffered: the loop writes as the socket drains
        return True

    async def run(self) -> None:
        """Keep a planner process running until cancelled (then kill it)."""
        started = 0
        try:
            while True:
                self._to(PlannerState.STARTING)
                reason = await self._run_once()
                self._to(PlannerState.LOST)
                started += 1
                self.restarts = started
                delay = self._backoff.next()
                _LOGGER.error("patrol: %s; starting another in %.1f s", reason, delay)
                self._on_lost(reason)
                await asyncio.sleep(delay)
        finally:
            self._to(PlannerState.CLOSED)

    async def _run_once(self) -> str:
        """Start a process and serve it until it dies: why it did."""
        ours, theirs = socket.socketpair(socket.AF_UNIX, socket.SOCK_STREAM)
        try:
            process = await asyncio.create_subprocess_exec(
                sys.executable, "-m", "brasidas.autonomy.planner_worker", str(theirs.fileno()),
                pass_fds=(theirs.fileno(),), stdin=asyncio.subprocess.DEVNULL,
                stdout=asyncio.subprocess.DEVNULL, start_new_session=True,
            )  # fmt: skip
        except OSError as exc:  # (out of processes, memory): tried again after the backoff
            ours.close()
            return f"the planner process could not start ({exc})"
        except BaseException:
            ours.close()
            raise
        finally:
            theirs.close()
        self.pid = process.pid
        writer: asyncio.StreamWriter | None = None
        try:
            reader, writer = await asyncio.open_unix_connection(sock=ours)
            self._writer = writer
            self._to(PlannerState.RUNNING)
            self._resent = None
            if self._map is not None:
                latest = self._map
                self._send(
                    {"op": "map", "revision": latest.revision, "clearance": latest.clearance},
                    latest.geojson,
                )
            try:
                await self._read(reader)
                why = "the socket closed"
            except (OSError, ValueError, asyncio.IncompleteReadError) as exc:
                why = str(exc) or type(exc).__name__
            with contextlib.suppress(ProcessLookupError):
                process.kill()
            code = await process.wait()
            return f"the planner process stopped (exit code {code}, {why})"
        finally:
            self._writer = None
            self.pid = None
            # Through its transport, which the loop then forgets: the socket closed under it
            # left the loop watching a number the next open reused ("File descriptor N is used
            # by transport" for a serial device opened after a stop).
            if writer is not None:
                writer.close()
            ours.close()
            if process.returncode is None:
                with contextlib.suppress(ProcessLookupError):
                    process.kill()
                # Reaped here (the daemon's stop waits for it): no process is left behind.
                with contextlib.suppress(asyncio.TimeoutError, asyncio.CancelledError):
                    await asyncio.wait_for(asyncio.shield(process.wait()), KILL_WAIT_S)

    async def _read(self, reader: asyncio.StreamReader) -> None:
        while True:
            head, size = parse_header(await reader.readexactly(HEADER.size))
            header = orjson.loads(await reader.readexactly(head))
            if size:
                await reader.readexactly(size)
            if isinstance(header, dict):
                self._backoff.reset()
                self._on_answer(header)
