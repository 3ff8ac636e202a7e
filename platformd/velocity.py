"""The velocity stream receiver: ``$PVEL`` datagrams from the override holder onto the bus.

A datagram moves the robot only when it parses, is in range, comes from the host of the
session holding the manual override, carries that session's tag (unless running insecure),
is newer than the last accepted one, and — when it carries its send time — is not older than
``velocity.max_age_ms`` on arrival (a burst of stale commands after a lag spike moves
nothing). Everything else is dropped and counted by reason, and refreshes nothing: only an
accepted, session-tagged packet is the holder's sign of life for the failsafe ladder, and only
accepted ones are aged for the speed cap. The counters go on ``VELOCITY_LINK_STATS`` and into
telemetry. Accepted velocities go on ``TELEOP_VELOCITY``; the
motion arbiter decides whether they reach the motors. The measured age of the holder's packets
goes on ``COMMAND_AGE``: the speed cap's command latency.
"""

from __future__ import annotations

import asyncio
import collections
import ipaddress
import logging
import time
from collections.abc import Callable
from typing import Any

from brasidas import topics
from brasidas.actor import Actor
from brasidas.codecs import pvel
from brasidas.codecs.pvel import DropReason, PvelSentence
from brasidas.codecs.telemetry_schema import VelocityLink
from brasidas.messages import (
    CommandAge,
    FailsafeState,
    FailsafeStep,
    OverrideState,
    Velocity,
    VelocityLinkStats,
)
from platformd.context import PlatformContext
from platformd.sessions import velocity_endpoint

_LOGGER = logging.getLogger(__name__)

AGE_WINDOW = 1.0
"""Seconds of accepted packets whose oldest age is the command latency (the speed cap's)."""
AGE_PUBLISH_INTERVAL = 0.2
"""How often the command age is republished as old samples leave the window (a rise is
published at once)."""


class Holder:
    """Who may drive: the override holder's session id, host and key."""

    __slots__ = ("host", "key", "session_id")

    def __init__(self, session_id: str, host: str, key: bytes | None) -> None:
        self.session_id = session_id
        self.host = normalize_host(host)
        self.key = key


class VelocityGate:
    """Sans-IO admission of ``$PVEL`` datagrams for the current override holder.

    ``require_tag`` is set whenever the platform has a fleet key: then an untagged sentence or
    one tagged with another key is dropped even from the right host.
    """

    def __init__(self, *, require_tag: bool, max_age_ms: float = float("inf")) -> None:
        self.require_tag = require_tag
        self.max_age_ms = max_age_ms
        self.holder: Holder | None = None
        self.held = False
        """The failsafe ladder holds: every datagram is dropped (``held``)."""
        self.last_count: int | None = None
        self.accepted = 0
        self.dropped: dict[DropReason, int] = dict.fromkeys(DropReason, 0)
        self.last_age_ms: float | None = None
        """The last accepted sentence's age on arrival, if it carried its send time."""
        self._ages: collections.deque[tuple[float, float]] = collections.deque()
        """(arrival s, age ms) of the accepted sentences of the last :data:`AGE_WINDOW`."""
        self._last_session: str | None = None

    def set_holder(self, holder: Holder | None) -> None:
        """Change who may drive. A new session starts a new count sequence; the same session
        re-engaging keeps its last count, so its old packets cannot be replayed."""
        self.holder = holder
        if holder is not None and holder.session_id != self._last_session:
            self._last_session = holder.session_id
            self.last_count = None
            self.last_age_ms = None
            self._ages.clear()

    def admit(self, datagram: bytes, host: str, now: float = 0.0) -> PvelSentence | DropReason:
        """Decide one datagram from ``host`` arriving at ``now`` (seconds of the monotonic
        clock the holder's station stamps in); counts the outcome."""
        age: float | None = None
        result = self._check(datagram, host)
        if isinstance(result, PvelSentence):
            age = pvel.age_ms(result, now * 1000)
            if age is not None and not -self.max_age_ms <= age <= self.max_age_ms:
                # Spent, not obeyed, like a held one (a later packet may be fresh again).
                self.last_count = result.count
                result = DropReason.STALE
        if isinstance(result, DropReason):
            self.dropped[result] += 1
            return result
        self.accepted += 1
        self.last_count = result.count
        if age is not None:
            # Slightly negative: the station's offset estimate is off by less than its error
            # (half a heartbeat's round trip); the packet is as fresh as can be measured.
            age = max(0.0, age)
            self.last_age_ms = age
            self._ages.append((now, age))
        return result

    def proves_life(self, result: PvelSentence | DropReason) -> bool:
        """``result`` (of :meth:`admit`) is a sign of the holder's life: accepted, and tagged
        with its session key. No drop counts (a replayed, stale, duplicate or held packet
        carries a genuine tag too), nor an untagged packet of an insecure platform (its source
        address is all that vouches for it)."""
        holder = self.holder
        return isinstance(result, PvelSentence) and holder is not None and holder.key is not None

    def command_age(self, now: float) -> CommandAge | None:
        """The oldest and the latest age of the sentences accepted in the last
        :data:`AGE_WINDOW` before ``now``; None without any that carried its send time."""
        ages = self._ages
        while ages and ages[0][0] < now - AGE_WINDOW:
            ages.popleft()
        if not ages:
            return None
        return CommandAge(max(age for _, age in ages), ages[-1][1], len(ages))

    def _check(self, datagram: bytes, host: str) -> PvelSentence | DropReason:
        sentence = pvel.decode(datagram)
        if isinstance(sentence, DropReason):
            return sentence
        holder = self.holder
        if holder is None:
            return DropReason.NOT_ENGAGED
        if host != holder.host and normalize_host(host) != holder.host:
            return DropReason.NOT_HOLDER
        if holder.key is not None:
            if not pvel.verify_tag(sentence, holder.key, holder.session_id):
                return DropReason.BAD_TAG
        elif self.require_tag:
            return DropReason.BAD_TAG
        if self.last_count is not None and sentence.count <= self.last_count:
            return DropReason.OUT_OF_ORDER
        if self.held:
            # Spent, not obeyed: after the operator re-engages, this count is already old.
            self.last_count = sentence.count
            return DropReason.HELD
        return sentence

    def stats(self, now: float | None = None) -> VelocityLinkStats:
        age = self.command_age(now) if now is not None else None
        return VelocityLinkStats(
            self.accepted,
            {reason.value: count for reason, count in self.dropped.items()},
            self.last_count,
            None if age is None else round(age.last_ms, 1),
            None if age is None else round(age.max_ms, 1),
        )


def normalize_host(host: str) -> str:
    """``::ffff:10.0.0.2`` and ``10.0.0.2`` are the same peer."""
    try:
        address = ipaddress.ip_address(host.split("%", 1)[0])
    except ValueError:
        return host
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        return str(address.ipv4_mapped)
    return str(address)


class _VelocityProtocol(asyncio.DatagramProtocol):
    def __init__(self, on_datagram: Callable[[bytes, str], None]) -> None:
        self._on_datagram = on_datagram

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        self._on_datagram(data, str(addr[0]))

    def error_received(self, exc: Exception) -> None:
        _LOGGER.debug("velocity socket error: %s", exc)


class VelocityReceiver(Actor):
    """Owns the bound UDP socket; publishes accepted velocities and the link counters."""

    name = "velocity"
    restart = False

    def __init__(
        self,
        ctx: PlatformContext,
        transport: asyncio.DatagramTransport | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self.gate = VelocityGate(
            require_tag=ctx.fleet_key is not None, max_age_ms=ctx.config.velocity.max_age_ms
        )
        self.transport = transport
        self._clock = clock
        """The clock of the heartbeat answers (``clock``) the stations estimate their offset to."""
        self._published: VelocityLinkStats | None = None
        self._age: CommandAge | None = None

    def on_datagram(self, data: bytes, host: str) -> None:
        """Socket callback: admit, then publish. Runs on the loop."""
        now = self._clock()
        result = self.gate.admit(data, host, now)
        if isinstance(result, PvelSentence):
            if self.gate.proves_life(result):
                self._heard_from_holder()
            age = self.gate.last_age_ms
            if age is not None and (self._age is None or age > self._age.max_ms):
                self.publish_age(now)  # an older packet than any of the window: at once
            self.bus.publish(topics.TELEOP_VELOCITY, Velocity(result.x, result.z))
        elif result is DropReason.NOT_HOLDER or result is DropReason.BAD_TAG:
            # Worth a log line, but a flood of spoofed packets must not flood the log.
            count = self.gate.dropped[result]
            if count & (count - 1) == 0:
                _LOGGER.warning(
                    "velocity from %s dropped (%s), %d so far", host, result.value, count
                )

    def _heard_from_holder(self) -> None:
        # The holder's accepted packets prove its link as a heartbeat does (for the failsafe
        # ladder, not for the session's timeout): at 20 Hz, a short cut is not taken for a lost
        # link. A dropped one proves nothing: a third host replays captured ones, tag and all.
        holder = self.gate.holder
        session = self.ctx.session(holder.session_id) if holder is not None else None
        if session is not None:
            session.last_velocity = time.monotonic()

    async def run(self) -> None:
        self.subscribe(topics.OVERRIDE_STATE, self._on_override)
        self.subscribe(topics.FAILSAFE_STATE, self._on_failsafe)
        self.subscribe(topics.SESSION_CLOSED, lambda _event: self._refresh_holder())
        self.bus.publish(topics.COMMAND_AGE, None)
        interval = self.ctx.config.velocity.stats_interval
        next_stats = self._clock() + interval
        try:
            while True:
                await asyncio.sleep(AGE_PUBLISH_INTERVAL)
                now = self._clock()
                self.publish_age(now)
                if now >= next_stats:
                    next_stats = now + interval
                    self.publish_stats()
        finally:
            self.close()

    def publish_stats(self) -> None:
        """Publish the counters if they changed since last time."""
        stats = self.gate.stats(self._clock())
        if stats != self._published:
            self._published = stats
            self.bus.publish(topics.VELOCITY_LINK_STATS, stats)

    def publish_age(self, now: float) -> None:
        """Publish the command age if it changed (by a millisecond or more)."""
        age = self.gate.command_age(now)
        previous = self._age
        if (age is None) != (previous is None) or (
            age is not None and previous is not None and abs(age.max_ms - previous.max_ms) >= 1.0
        ):
            self._age = age
            self.bus.publish(topics.COMMAND_AGE, age)

    def link_section(self) -> VelocityLink:
        """The counters and the command age as the ``velocity_link`` telemetry section."""
        stats = self.gate.stats(self._clock())
        return VelocityLink(
            stats.accepted, stats.dropped, stats.last_count, stats.age_ms, stats.age_max_ms
        )

    def _on_override(self, state: OverrideState) -> None:
        self._refresh_holder(state)
        self.publish_stats()

    def _on_failsafe(self, state: FailsafeState) -> None:
        self.gate.held = state.step is FailsafeStep.HOLD

    def _refresh_holder(self, state: OverrideState | None = None) -> None:
        state = state or self.bus.last(topics.OVERRIDE_STATE)
        holder: Holder | None = None
        if state is not None and state.engaged and state.session_id is not None:
            session = self.ctx.session(state.session_id)
            if session is not None:
                holder = Holder(session.session_id, session.peer_host, session.session_key)
        self.gate.set_holder(holder)

    def close(self) -> None:
        """Close the socket. Idempotent."""
        if self.transport is not None:
            self.transport.close()
            self.transport = None


async def open_receiver(ctx: PlatformContext) -> VelocityReceiver:
    """Bind the velocity socket (a busy port fails here, at startup) and build the receiver."""
    config = ctx.config.velocity
    receiver = VelocityReceiver(ctx)
    loop = asyncio.get_running_loop()
    transport, _ = await loop.create_datagram_endpoint(
        lambda: _VelocityProtocol(receiver.on_datagram), local_addr=(config.host, config.port)
    )
    receiver.transport = transport
    ctx.velocity_port = int(transport.get_extra_info("sockname")[1])  # 0: the kernel's choice
    return receiver


def capability(ctx: PlatformContext) -> dict[str, Any]:
    """The ``velocity`` section of the connect answer."""
    return {
        **velocity_endpoint(ctx),
        "format": "$PVEL,<count>,<x>,<z>[,<sent>][,<tag>]*<checksum>",
        "max_age_ms": ctx.config.velocity.max_age_ms,
        "tag_bytes": pvel.TAG_BYTES if ctx.fleet_key is not None else 0,
        "deadman_s": ctx.config.velocity.deadman,
    }


async def async_setup(ctx: PlatformContext) -> None:
    receiver = await open_receiver(ctx)
    ctx.capabilities.register("velocity", lambda: capability(ctx))
    ctx.telemetry.register(VelocityLink, receiver.link_section)
    ctx.supervisor.start(receiver)
