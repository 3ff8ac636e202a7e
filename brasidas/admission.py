"""Admission before work: which TCP connections a server holds, and for how long.

A connection without a session is a stranger's: strangers are capped per source address and
in total (past a cap, the oldest stranger of the address, once held a second, or of the
busiest address, is closed for the newcomer; a connection that proves the key stops
counting), must send their headers and bodies within a timeout and are closed when idle.
Every connection is capped in total (below the process's file descriptor limit, less a
reserve for the daemon's own files, pipelines and serial lines), and closed when its unsent
data grows past a bound or stops draining (a reader that does not read is closed, never
buffered for).

:class:`AdmissionPolicy` decides (sans-IO, ``now`` passed in); :class:`AdmittingListener`
accepts on a listening socket through it, without spinning when the process is out of file
descriptors (it backs off and logs once per interval), and hands each admitted connection to
the server's protocol (aiohttp's) behind :class:`AdmittedProtocol`, over TLS when given a
context.
"""

from __future__ import annotations

import asyncio
import enum
import errno
import logging
import resource
import socket
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

from brasidas.config.admission import AdmissionSection, StrangerAdmissionSection
from brasidas.states import Transitions

if TYPE_CHECKING:
    from ssl import SSLContext  # only the station's HTTPS console: the platform keeps ssl out

_LOGGER = logging.getLogger(__name__)

SWEEP_INTERVAL = 0.25
"""Seconds between checks of the timeouts and of unsent data."""
ACCEPT_BATCH = 64
"""Connections accepted per readiness event, at most (the loop turns between batches)."""
ACCEPT_BACKOFF_INITIAL = 0.05
ACCEPT_BACKOFF_MAX = 1.0
"""Seconds before accepting again after the process ran out of file descriptors (doubling)."""
LOG_INTERVAL = 10.0
"""A repeated admission problem (out of descriptors, refusals) is logged once per interval."""
REFUSAL_WINDOW = 10.0
"""Seconds over which refused connections are tallied per source address."""
MAX_TALLIED_HOSTS = 256
"""Addresses tallied per window, at most (the first ones refused; the rest are only counted)."""
COUNTERS = (
    "accepted",
    "refused_host",
    "evicted_host",
    "refused_full",
    "evicted",
    "header_timeouts",
    "body_timeouts",
    "idle_timeouts",
    "slow_readers",
    "out_of_descriptors",
    "throttled",
)
"""The admission's counters (:attr:`AdmissionPolicy.counters`); telemetry carries all but
``accepted``."""
_OUT_OF_RESOURCES = (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM)


@dataclass(frozen=True)
class AdmissionLimits:
    """What a server lets connections hold; ``trusted``: every connection counts as having a
    session (the station's local API, which has none and answers its own host only)."""

    max_connections: int = 512
    max_strangers: int = 64
    max_strangers_per_host: int = 8
    header_timeout: float = 5.0
    body_timeout: float = 5.0
    idle_timeout: float = 15.0
    write_timeout: float = 10.0
    max_unsent_bytes: int = 1 << 20
    reserved_fds: int = 128
    host_evict_after: float = 1.0
    """An address at its cap: its oldest stranger held this long (s) is closed for a newcomer;
    younger, the newcomer is refused."""
    stranger_bytes_per_s: int = 16384
    """What all of one address's strangers may send, on average (a burst of twice as much)."""
    trusted: bool = False


def admission_limits(section: AdmissionSection) -> AdmissionLimits:
    """The limits of a daemon's ``[admission]`` section. A server without sessions (the
    station's local API: only the section's common keys) treats every connection as trusted."""
    common = AdmissionLimits(
        max_connections=section.max_connections,
        max_strangers=section.max_connections,
        max_strangers_per_host=section.max_connections,
        header_timeout=section.header_timeout,
        body_timeout=section.body_timeout,
        idle_timeout=section.idle_timeout,
        write_timeout=section.write_timeout,
        max_unsent_bytes=section.max_unsent_bytes,
        reserved_fds=section.reserved_fds,
        trusted=True,
    )
    if not isinstance(section, StrangerAdmissionSection):
        return common
    return replace(
        common,
        max_strangers=section.max_strangers,
        max_strangers_per_host=section.max_strangers_per_host,
        stranger_bytes_per_s=section.stranger_bytes_per_s,
        trusted=False,
    )


def fd_limit() -> int:
    """The process's soft limit on open file descriptors."""
    return resource.getrlimit(resource.RLIMIT_NOFILE)[0]


@dataclass
class RefusalTally:
    """Connections refused (or evicted) per source address, over fixed windows. Sans-IO."""

    window: float = REFUSAL_WINDOW
    started: float | None = None
    current: dict[str, int] = field(default_factory=dict)
    """The window under way (since ``started``)."""
    previous: dict[str, int] = field(default_factory=dict)
    """The last whole window, if it ended less than a window ago."""

    def count(self, host: str, now: float) -> None:
        self._roll(now)
        current = self.current
        if host in current or len(current) < MAX_TALLIED_HOSTS:
            current[host] = current.get(host, 0) + 1

    def top(self, now: float) -> tuple[str, int]:
        """The address refused most in the last whole window or the one under way (each
        at most ``window`` seconds), with its count; ``("", 0)`` when none was."""
        self._roll(now)
        best = ("", 0)
        for tally in (self.previous, self.current):
            for host, refused in tally.items():
                if refused > best[1]:
                    best = (host, refused)
        return best

    def _roll(self, now: float) -> None:
        if self.started is None:
            self.started = now
            return
        elapsed = now - self.started
        if elapsed < self.window:
            return
        self.previous = self.current if elapsed < 2 * self.window else {}
        self.current = {}
        self.started = now - elapsed % self.window


class SlotState(enum.Enum):
    STRANGER = "stranger"
    """No call on the connection has a session yet: capped per address and in all."""
    SESSION = "session"
    """A call has a session (or the listener is a trusted one): no stranger's caps."""
    CLOSED = "closed"
    """Released: the connection closed, or was evicted for a newcomer."""


SLOT_TRANSITIONS = Transitions[SlotState](
    "admission slot",
    {
        SlotState.STRANGER: frozenset((SlotState.SESSION, SlotState.CLOSED)),
        SlotState.SESSION: frozenset((SlotState.CLOSED,)),
    },
)


@dataclass(eq=False, slots=True)
class Slot:
    """One admitted connection, as the policy sees it."""

    host: str
    opened: float
    last_read: float
    idle_since: float
    """When the connection last had no request in progress (its start, or a request's end)."""
    read_while_idle: bool = False
    """Bytes came since ``idle_since``: a request's headers have begun."""
    headers_since: float = 0.0
    """When the first of those bytes came."""
    requests: int = 0
    """Requests in progress (a WebSocket is one for its whole life)."""
    stalled_since: float | None = None
    """Since when its unsent data has not shrunk."""
    unsent: int = 0
    state: SlotState = SlotState.STRANGER

    @property
    def has_session(self) -> bool:
        return self.state is SlotState.SESSION

    @property
    def closed(self) -> bool:
        return self.state is SlotState.CLOSED

    def to(self, state: SlotState) -> None:
        self.state = SLOT_TRANSITIONS.check(self.state, state)


@dataclass
class AdmissionPolicy:
    """Decides admission and timeouts for one server. Functions take ``now`` (loop time)."""

    limits: AdmissionLimits
    descriptors: int = field(default_factory=fd_limit)
    """The file descriptor limit the capacity is computed from."""
    slots: set[Slot] = field(default_factory=set)
    strangers: dict[str, list[Slot]] = field(default_factory=dict)
    """Connections without a session, by source address, oldest first."""
    budgets: dict[str, tuple[float, float]] = field(default_factory=dict)
    """Per address whose strangers sent something: bytes it may still send, and when."""
    refusals: RefusalTally = field(default_factory=RefusalTally)
    """Refused and evicted connections per address, lately (the station's warning)."""
    counters: dict[str, int] = field(default_factory=lambda: dict.fromkeys(COUNTERS, 0))

    @property
    def capacity(self) -> int:
        """Connections held at most: ``max_connections``, below the descriptor limit less the
        reserve (never less than 1)."""
        limits = self.limits
        return max(1, min(limits.max_connections, self.descriptors - limits.reserved_fds))

    def capacity_shortfall(self) -> str | None:
        """Why fewer than ``max_connections`` can be held (the open-file limit), or None."""
        limits = self.limits
        if self.capacity >= limits.max_connections:
            return None
        return (
            f"the open-file limit ({self.descriptors}) less reserved_fds ({limits.reserved_fds}) "
            f"holds {self.capacity} connections, fewer than max_connections "
            f"({limits.max_connections}): raise the limit (LimitNOFILE, ulimit -n)"
        )

    @property
    def stranger_count(self) -> int:
        return sum(len(slots) for slots in self.strangers.values())

    def admit(self, host: str, now: float) -> tuple[Slot | None, Slot | None]:
        """The new connection's slot (None: refused) and the stranger's connection it evicts."""
        limits = self.limits
        if len(self.slots) >= self.capacity:
            self.counters["refused_full"] += 1
            self.refusals.count(host, now)
            return None, None
        evicted = None
        if not limits.trusted:
            same_host = self.strangers.get(host, [])
            if len(same_host) >= limits.max_strangers_per_host:
                # Behind one address (NAT) a station may share it with whoever holds its cap:
                # the address's oldest stranger goes for the newcomer, which needs its slot
                # only until it proves the key. A younger one stays (the newcomer is refused)
                # so that a host opening connections as fast as it can churns at most
                # max_strangers_per_host / host_evict_after of them a second, not all.
                oldest = same_host[0]
                self.refusals.count(host, now)
                if now - oldest.opened < limits.host_evict_after:
                    self.counters["refused_host"] += 1
                    return None, None
                evicted = oldest
                self.release(evicted)
                self.counters["evicted_host"] += 1
            elif self.stranger_count >= limits.max_strangers:
                # The oldest of the host that holds the most goes: one busy host cannot keep
                # a station from another out.
                crowded = max(self.strangers.values(), key=len)
                evicted = crowded[0]
                self.release(evicted)
                self.counters["evicted"] += 1
                self.refusals.count(evicted.host, now)
        slot = Slot(
            host, now, now, now, state=SlotState.SESSION if limits.trusted else SlotState.STRANGER
        )
        self.slots.add(slot)
        if not slot.has_session:
            self.strangers.setdefault(host, []).append(slot)
        self.counters["accepted"] += 1
        return slot, evicted

    def release(self, slot: Slot) -> None:
        """The connection closed (idempotent)."""
        if slot.closed:
            return
        slot.to(SlotState.CLOSED)
        self.slots.discard(slot)
        self._forget_stranger(slot)

    def session_opened(self, slot: Slot) -> None:
        """A call on the connection has a session: it is no longer a stranger's (a slot
        released meanwhile stays closed)."""
        if slot.state is SlotState.STRANGER:
            slot.to(SlotState.SESSION)
            self._forget_stranger(slot)

    def received(self, slot: Slot, now: float) -> None:
        slot.last_read = now
        if not slot.read_while_idle:
            slot.read_while_idle = True
            slot.headers_since = now

    def charge(self, slot: Slot, size: int, now: float) -> float:
        """Count ``size`` bytes received on ``slot``: seconds to stop reading it for (0: go
        on). A stranger's address has a byte budget (a token bucket); a station has none."""
        if slot.has_session:
            return 0.0
        rate = self.limits.stranger_bytes_per_s
        burst = 2.0 * rate
        left, since = self.budgets.get(slot.host, (burst, now))
        left = min(burst, left + (now - since) * rate) - size
        self.budgets[slot.host] = (left, now)
        if len(self.budgets) > 2 * self.limits.max_strangers:
            self._forget_full_budgets(now)
        if left >= 0:
            return 0.0
        self.counters["throttled"] += 1
        return -left / rate

    def _forget_full_budgets(self, now: float) -> None:
        """Addresses whose budget has refilled cost nothing to forget (the table stays small)."""
        rate = self.limits.stranger_bytes_per_s
        for host, (left, since) in list(self.budgets.items()):
            if left + (now - since) * rate >= 2.0 * rate:
                del self.budgets[host]

    def request_started(self, slot: Slot) -> None:
        slot.requests += 1

    def request_ended(self, slot: Slot, now: float) -> None:
        slot.requests -= 1
        if slot.requests == 0:
            slot.idle_since = now
            slot.read_while_idle = False

    def due(self, now: float, unsent: Callable[[Slot], int]) -> list[tuple[Slot, str]]:
        """The connections to close at ``now``, each with its reason (counted)."""
        limits = self.limits
        closing: list[tuple[Slot, str]] = []
        for slot in self.slots:
            reason = self._overdue(slot, now, unsent(slot), limits)
            if reason is not None:
                closing.append((slot, reason))
                self.counters[reason] += 1
        return closing

    def _overdue(self, slot: Slot, now: float, unsent: int, limits: AdmissionLimits) -> str | None:
        if unsent > limits.max_unsent_bytes:
            return "slow_readers"
        if unsent == 0 or unsent < slot.unsent:
            slot.stalled_since = None
        elif slot.stalled_since is None:
            slot.stalled_since = now
        elif now - slot.stalled_since > limits.write_timeout:
            return "slow_readers"
        slot.unsent = unsent
        if slot.requests == 0:
            if slot.read_while_idle:
                if now - slot.headers_since > limits.header_timeout:
                    return "header_timeouts"
            elif now - slot.idle_since > limits.idle_timeout:
                return "idle_timeouts"
        elif not slot.has_session and now - slot.last_read > limits.idle_timeout:
            return "idle_timeouts"  # a stranger's WebSocket (or body) that went quiet
        return None

    def _forget_stranger(self, slot: Slot) -> None:
        same_host = self.strangers.get(slot.host)
        if same_host is not None and slot in same_host:
            same_host.remove(slot)
            if not same_host:
                del self.strangers[slot.host]


class AdmittedProtocol(asyncio.Protocol):
    """The server's protocol for one admitted connection, seen by the listener on the way.

    A stranger over its address's byte budget is not read for a while: what already came is
    held back (one read's worth) and handed on when the budget allows, so a flood costs the
    kernel's buffers, not the event loop.
    """

    __slots__ = ("_held", "_inner", "_listener", "_resume", "_transport", "slot")

    def __init__(self, listener: AdmittingListener, slot: Slot, inner: asyncio.Protocol) -> None:
        self._listener = listener
        self.slot = slot
        self._inner = inner
        self._transport: asyncio.Transport | None = None
        self._held: list[bytes] = []
        self._resume: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        self._transport = transport
        self._listener.opened(self.slot, transport)
        self._inner.connection_made(transport)

    def data_received(self, data: bytes) -> None:
        listener = self._listener
        now = listener.loop.time()
        listener.policy.received(self.slot, now)
        if self._resume is not None:  # throttled, and read all the same (aiohttp resumed)
            self._held.append(data)
            self._pause()
            return
        delay = listener.policy.charge(self.slot, len(data), now)
        if delay <= 0:
            self._inner.data_received(data)
            return
        self._held.append(data)
        self._pause()
        self._resume = listener.loop.call_later(delay, self._release)

    def _pause(self) -> None:
        if self._transport is not None and self._transport.is_reading():
            self._transport.pause_reading()

    def _release(self) -> None:
        """The budget allows again: hand on what was held, read on."""
        self._resume = None
        held, self._held = self._held, []
        transport = self._transport
        if transport is None or transport.is_closing():
            return
        transport.resume_reading()
        for data in held:
            self._inner.data_received(data)

    def eof_received(self) -> bool | None:
        return self._inner.eof_received()

    def pause_writing(self) -> None:
        self._inner.pause_writing()

    def resume_writing(self) -> None:
        self._inner.resume_writing()

    def connection_lost(self, exc: Exception | None) -> None:
        if self._resume is not None:
            self._resume.cancel()
            self._resume = None
        self._held.clear()
        self._listener.closed(self.slot)
        self._inner.connection_lost(exc)


class AdmittingListener:
    """Accepts on ``sock`` through ``policy``; each admitted connection is served by
    ``protocol_factory()``. Runs on the event loop (``start``, ``close`` and ``sweep``)."""

    def __init__(
        self,
        sock: socket.socket,
        protocol_factory: Callable[[], asyncio.Protocol],
        policy: AdmissionPolicy,
        name: str,
        *,
        ssl: SSLContext | None = None,
    ) -> None:
        self.sock = sock
        self.ssl = ssl
        """Connections are TLS, their handshake within the policy's ``header_timeout``."""
        self.policy = policy
        self.name = name
        self.loop = asyncio.get_running_loop()
        self._factory = protocol_factory
        self._transports: dict[Slot, asyncio.Transport] = {}
        self._by_transport: dict[asyncio.BaseTransport, Slot] = {}
        self._handshakes: set[asyncio.Task[None]] = set()
        self._resume: asyncio.TimerHandle | None = None
        self._backoff = ACCEPT_BACKOFF_INITIAL
        self._accepting = False
        self._logged: dict[str, float] = {}

    def start(self) -> None:
        self.sock.setblocking(False)
        self._accepting = True
        self.loop.add_reader(self.sock.fileno(), self._accept)

    def slot_of(self, transport: asyncio.BaseTransport | None) -> Slot | None:
        return self._by_transport.get(transport) if transport is not None else None

    async def sweep(self) -> None:
        """Close what is overdue, every :data:`SWEEP_INTERVAL`, until cancelled."""
        while True:
            await asyncio.sleep(SWEEP_INTERVAL)
            self.close_overdue(self.loop.time())

    def close_overdue(self, now: float) -> None:
        for slot, reason in self.policy.due(now, self._unsent):
            transport = self._transports.get(slot)
            self._log_once(reason, f"{self.name}: closing a connection from {slot.host} ({reason})")
            if transport is not None:
                transport.abort()
            self.policy.release(slot)

    def close(self) -> None:
        """Stop accepting (idempotent); admitted connections stay with the server's own
        shutdown."""
        if self._resume is not None:
            self._resume.cancel()
            self._resume = None
        if self._accepting:
            self._accepting = False
            self.loop.remove_reader(self.sock.fileno())
        if self.sock.fileno() != -1:
            self.sock.close()
        for task in self._handshakes:
            task.cancel("listener closed")

    def opened(self, slot: Slot, transport: asyncio.BaseTransport) -> None:
        assert isinstance(transport, asyncio.Transport)
        if slot.closed:  # evicted before its transport was made
            transport.abort()
            return
        self._transports[slot] = transport
        self._by_transport[transport] = slot

    def closed(self, slot: Slot) -> None:
        transport = self._transports.pop(slot, None)
        if transport is not None:
            self._by_transport.pop(transport, None)
        self.policy.release(slot)

    def _unsent(self, slot: Slot) -> int:
        transport = self._transports.get(slot)
        return transport.get_write_buffer_size() if transport is not None else 0

    def _accept(self) -> None:
        for _ in range(ACCEPT_BATCH):
            try:
                conn, address = self.sock.accept()
            except (BlockingIOError, InterruptedError):
                return
            except ConnectionAbortedError:
                continue
            except OSError as err:
                if err.errno in _OUT_OF_RESOURCES:
                    self._out_of_resources(err)
                    return
                _LOGGER.warning("%s: accept failed: %s", self.name, err)
                return
            self._backoff = ACCEPT_BACKOFF_INITIAL
            self._admit(conn, str(address[0]) if isinstance(address, tuple) else "")

    def _admit(self, conn: socket.socket, host: str) -> None:
        slot, evicted = self.policy.admit(host, self.loop.time())
        if evicted is not None:
            self._log_once(
                "evicted", f"{self.name}: closing strangers from {evicted.host} (over cap)"
            )
            if (transport := self._transports.get(evicted)) is not None:
                transport.abort()
        if slot is None:
            self._log_once("refused", f"{self.name}: refusing connections from {host} (over cap)")
            conn.close()
            return
        conn.setblocking(False)
        with_slot = slot

        def protocol() -> asyncio.Protocol:
            return AdmittedProtocol(self, with_slot, self._factory())

        task = self.loop.create_task(self._handshake(conn, protocol, slot))
        self._handshakes.add(task)
        task.add_done_callback(self._handshakes.discard)

    async def _handshake(
        self, conn: socket.socket, protocol: Callable[[], asyncio.Protocol], slot: Slot
    ) -> None:
        try:
            if self.ssl is None:
                await self.loop.connect_accepted_socket(protocol, conn)
            else:
                await self.loop.connect_accepted_socket(
                    protocol,
                    conn,
                    ssl=self.ssl,
                    ssl_handshake_timeout=self.policy.limits.header_timeout,
                )
        except BaseException as err:
            conn.close()
            self.policy.release(slot)
            if not isinstance(err, Exception):
                raise
            _LOGGER.debug("%s: connection from %s failed at once: %s", self.name, slot.host, err)

    def _out_of_resources(self, err: OSError) -> None:
        """Out of descriptors: stop accepting for a while (never spin on a ready socket)."""
        self.policy.counters["out_of_descriptors"] += 1
        self._log_once(
            "out_of_descriptors",
            f"{self.name}: cannot accept ({err.strerror}); retrying in {self._backoff:.2f} s",
        )
        if self._accepting:
            self._accepting = False
            self.loop.remove_reader(self.sock.fileno())
        self._resume = self.loop.call_later(self._backoff, self._resume_accepting)
        self._backoff = min(self._backoff * 2, ACCEPT_BACKOFF_MAX)

    def _resume_accepting(self) -> None:
        self._resume = None
        if not self._accepting and self.sock.fileno() != -1:
            self._accepting = True
            self.loop.add_reader(self.sock.fileno(), self._accept)

    def _log_once(self, kind: str, message: str) -> None:
        now = self.loop.time()
        last = self._logged.get(kind)
        if last is None or now - last >= LOG_INTERVAL:
            self._logged[kind] = now
            _LOGGER.warning("%s (counters: %s)", message, self.policy.counters)


@dataclass
class ServerAdmission:
    """An app's admission: its limits and the listeners that hold its connections."""

    limits: AdmissionLimits
    listeners: list[AdmittingListener] = field(default_factory=list)

    def slot_of(
        self, transport: asyncio.BaseTransport | None
    ) -> tuple[AdmittingListener, Slot] | None:
        for listener in self.listeners:
            slot = listener.slot_of(transport)
            if slot is not None:
                return listener, slot
        return None

    def counters(self) -> dict[str, int]:
        """Every listener's admission counters, added up."""
        total: dict[str, int] = {}
        for listener in self.listeners:
            for name, value in listener.policy.counters.items():
                total[name] = total.get(name, 0) + value
        return total

    def stranger_count(self) -> int:
        """Connections without a session held now."""
        return sum(listener.policy.stranger_count for listener in self.listeners)

    def top_refused(self, now: float) -> tuple[str, int]:
        """The address refused most lately on any listener (:meth:`RefusalTally.top`)."""
        best = ("", 0)
        for listener in self.listeners:
            found = listener.policy.refusals.top(now)
            if found[1] > best[1]:
                best = found
        return best


# --------------------------------------------------------------------------- bytes sent out

EGRESS_KINDS = ("mavlink", "rtp", "download")
"""What the robot sends on a source's behalf: MAVLink answers and telemetry, the video a
MAVLink request started, recording downloads."""
STRANGER_WINDOW_S = 10.0
"""A stranger is sent at most the bytes it sent in each window of this long (unspent credit
goes with the window: silence earns nothing)."""
ACTIVE_DOWNLOADER_S = 1.0
"""A source that reserved a download chunk this recently shares the download rate."""
MAX_SOURCES = 1024
"""Accounts kept at once: made-up source addresses cost a bounded table (the least recently
used account goes; a stranger's forgotten credit is credit lost, never gained)."""


@dataclass(slots=True)
class SourceAccount:
    """One source address's account."""

    received: int = 0
    """A stranger's bytes received (all time): what its answers are paid with."""
    sent: dict[str, int] = field(default_factory=lambda: dict.fromkeys(EGRESS_KINDS, 0))
    """Bytes sent on its behalf, by kind (all time)."""
    credit: int = 0
    """A stranger's bytes received in this window and not yet spent on answers."""
    window_since: float = -float("inf")
    download_free_at: float = -float("inf")
    """When its next download chunk may go (its share of the download rate)."""

    @property
    def total_sent(self) -> int:
        return sum(self.sent.values())


@dataclass
class SourceLedger:
    """Every byte the robot sends on a source address's behalf, through one account per
    address, whatever the path (sans-IO: ``now`` passed in).

    - A stranger (not proved the fleet or signing key, not a configured target) is paid only
      with what it sent: over each :data:`STRANGER_WINDOW_S`, bytes out ≤ bytes in, whatever
      it asks for (MAVLink answers, telemetry, video), so a spoofed source address never
      turns the robot into a reflector.
    - A stream (RTP) runs for trusted sources only: its cost is unbounded for a request of
      44 bytes. What it sends is charged to the source all the same.
    - Downloads (sessions only) share ``download_rate`` for all sources together, each source
      at most an equal part of it while others download (a source's parallel downloads are
      one source's).
    """

    download_rate: float = 0.0
    """Bytes a second for every download together (0: unlimited)."""
    stranger_window: float = STRANGER_WINDOW_S
    max_sources: int = MAX_SOURCES
    accounts: dict[str, SourceAccount] = field(default_factory=dict)
    """By source address, least recently used first."""
    counters: dict[str, int] = field(
        default_factory=lambda: dict.fromkeys(
            ("stranger_bytes_held", "streams_refused", "streams_stopped", "sources_forgotten"),
            0,
        )
    )

    def account(self, host: str) -> SourceAccount:
        """``host``'s account (made, or moved to most recently used)."""
        accounts = self.accounts
        account = accounts.pop(host, None)
        if account is None:
            account = SourceAccount()
            if len(accounts) >= self.max_sources:
                del accounts[next(iter(accounts))]
                self.counters["sources_forgotten"] += 1
        accounts[host] = account
        return account

    def sent_to(self, host: str) -> dict[str, int]:
        """Bytes sent on ``host``'s behalf by kind (zeros when it has no account)."""
        account = self.accounts.get(host)
        return dict(account.sent) if account is not None else dict.fromkeys(EGRESS_KINDS, 0)

    def received(self, host: str, size: int, now: float) -> None:
        """``size`` bytes came from ``host``: a stranger's credit for this window."""
        account = self._renewed(host, now)
        account.received += size
        account.credit += size

    def stranger_send(self, host: str, size: int, now: float, kind: str = "mavlink") -> bool:
        """May ``size`` bytes go to the stranger ``host`` now? Charged when they may, counted
        as held when not (all or nothing: a half answer is no answer)."""
        account = self._renewed(host, now)
        if size > account.credit:
            self.counters["stranger_bytes_held"] += size
            return False
        account.credit -= size
        account.sent[kind] += size
        return True

    def trusted_send(self, host: str, size: int, kind: str) -> None:
        """``size`` bytes went to a trusted ``host`` (counted, never held)."""
        self.account(host).sent[kind] += size

    def admits_stream(self, host: str, trusted: bool) -> bool:
        """May a stream start for ``host``? Trusted sources only (counted when refused)."""
        self.account(host)
        if not trusted:
            self.counters["streams_refused"] += 1
        return trusted

    def stream_sent(self, host: str, size: int, trusted: bool, now: float) -> bool:
        """A stream sent ``size`` more bytes to ``host``: charged; False when ``host`` is no
        longer trusted and its credit does not cover them (the stream must stop)."""
        if trusted:
            self.trusted_send(host, size, "rtp")
            return True
        if self.stranger_send(host, size, now, "rtp"):
            return True
        self.account(host).sent["rtp"] += size  # sent already: counted all the same
        self.counters["streams_stopped"] += 1
        return False

    def reserve_download(self, host: str, size: int, now: float) -> float:
        """Seconds to wait before sending ``size`` bytes of a download to ``host``, reserved
        (and charged) at once: the next caller waits behind them. Each source downloading
        lately gets an equal part of the rate."""
        account = self.account(host)
        account.sent["download"] += size
        rate = self.download_rate
        if rate <= 0:
            return 0.0
        sharing = 1 + sum(
            1
            for other, peer in self.accounts.items()
            if other != host and peer.download_free_at > now - ACTIVE_DOWNLOADER_S
        )
        # Each source on a timeline of its own at its part of the rate: one source's queue of
        # parallel downloads never delays another's (all together: the rate, give or take the
        # chunks reserved before a newcomer changed the parts).
        start = max(now, account.download_free_at)
        account.download_free_at = start + size * sharing / rate
        return start - now

    def _renewed(self, host: str, now: float) -> SourceAccount:
        account = self.account(host)
        if now - account.window_since >= self.stranger_window:
            account.window_since = now
            account.credit = 0
        return account
