"""Velocity stream and mode arbitration: admission rules, deadman, override, over real UDP."""

from __future__ import annotations

import asyncio
import functools
import os
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass, field

from conftest import quiet_platform_config, wait_until
from support.velocity import open_connection, udp_socket

from brasidas import topics
from brasidas.bus import Bus
from brasidas.codecs import pvel
from brasidas.codecs.pvel import DropReason, PvelSentence
from brasidas.codecs.telemetry_schema import Motion, VelocityLink
from brasidas.messages import Mode, OverrideState, Velocity
from platformd.app import PlatformDaemon
from platformd.arbiter import STOP, MotionArbiter
from platformd.velocity import Holder, VelocityGate, normalize_host

Factory = Callable[..., Awaitable[PlatformDaemon]]
KEY = os.urandom(32)
OTHER_KEY = os.urandom(32)


# --------------------------------------------------------------------------- admission (sans-IO)


def tagged(count: int, x: float = 0.1, z: float = 0.2, key: bytes = KEY, sid: str = "s1") -> bytes:
    return pvel.encode(count, x, z, key=key, session_id=sid)


def test_nothing_moves_without_an_override_holder() -> None:
    gate = VelocityGate(require_tag=True)
    assert gate.admit(tagged(1), "127.0.0.1") is DropReason.NOT_ENGAGED
    assert gate.stats().dropped["not_engaged"] == 1
    assert gate.accepted == 0


def test_holder_host_tag_and_order() -> None:
    gate = VelocityGate(require_tag=True)
    gate.set_holder(Holder("s1", "127.0.0.1", KEY))
    assert isinstance(gate.admit(tagged(5), "127.0.0.1"), PvelSentence)
    assert gate.admit(tagged(5), "127.0.0.1") is DropReason.OUT_OF_ORDER  # duplicate
    assert gate.admit(tagged(4), "127.0.0.1") is DropReason.OUT_OF_ORDER  # late
    assert gate.admit(tagged(6), "127.0.0.2") is DropReason.NOT_HOLDER  # spoofed source
    assert gate.admit(tagged(6, key=OTHER_KEY), "127.0.0.1") is DropReason.BAD_TAG
    assert gate.admit(tagged(6, sid="s2"), "127.0.0.1") is DropReason.BAD_TAG  # other session
    assert gate.admit(pvel.encode(6, 0.1, 0.2), "127.0.0.1") is DropReason.BAD_TAG  # untagged
    # None of the rejected packets advanced the count: 6 is still the next good one.
    assert isinstance(gate.admit(tagged(6), "127.0.0.1"), PvelSentence)
    assert gate.admit(b"$PVEL,7,0.1,0.2*00", "127.0.0.1") is DropReason.BAD_CHECKSUM
    assert gate.admit(b"hello", "127.0.0.1") is DropReason.MALFORMED
    stats = gate.stats()
    assert stats.accepted == 2
    assert stats.last_count == 6
    assert stats.dropped == {
        "malformed": 1,
        "bad_checksum": 1,
        "out_of_range": 0,
        "out_of_order": 2,
        "not_engaged": 0,
        "not_holder": 1,
        "bad_tag": 3,
        "stale": 0,
        "held": 0,
    }


def test_packets_are_aged_and_stale_ones_dropped_counted_and_spent() -> None:
    gate = VelocityGate(require_tag=True, max_age_ms=500)
    gate.set_holder(Holder("s1", "127.0.0.1", KEY))
    now = 1000.0  # seconds of the platform's clock; packets carry ms of it

    def stamped(count: int, age_ms: float) -> bytes:
        return pvel.encode(
            count, 0.1, 0.2, key=KEY, session_id="s1", sent_ms=int(now * 1000 - age_ms)
        )

    assert isinstance(gate.admit(stamped(1, 120), "127.0.0.1", now), PvelSentence)
    assert gate.last_age_ms == 120
    assert gate.admit(stamped(2, 501), "127.0.0.1", now) is DropReason.STALE
    assert gate.admit(stamped(3, -501), "127.0.0.1", now) is DropReason.STALE  # from the future
    # A stale packet is spent: it cannot be obeyed later, nor can an older count.
    assert gate.admit(stamped(3, 10), "127.0.0.1", now) is DropReason.OUT_OF_ORDER
    assert isinstance(gate.admit(stamped(4, -3), "127.0.0.1", now), PvelSentence)
    assert gate.last_age_ms == 0  # clock estimate slightly ahead: as fresh as measurable
    # An older sender's untimed packet is accepted with no age.
    untimed = pvel.encode(5, 0.1, 0.2, key=KEY, session_id="s1")
    assert isinstance(gate.admit(untimed, "127.0.0.1", now), PvelSentence)
    age = gate.command_age(now + 0.5)
    assert age is not None
    assert age.max_ms == 120
    assert age.last_ms == 0
    assert age.samples == 2
    assert gate.command_age(now + 1.01) is None  # the window is a second
    stats = gate.stats(now)
    assert stats.dropped["stale"] == 2
    assert stats.accepted == 3


def test_a_session_key_is_required_whenever_the_platform_has_a_fleet_key() -> None:
    gate = VelocityGate(require_tag=True)
    gate.set_holder(Holder("s1", "127.0.0.1", None))
    assert gate.admit(pvel.encode(1, 0, 0), "127.0.0.1") is DropReason.BAD_TAG


def test_insecure_platform_checks_the_host_only() -> None:
    gate = VelocityGate(require_tag=False)
    gate.set_holder(Holder("s1", "127.0.0.1", None))
    assert isinstance(gate.admit(pvel.encode(1, 0.5, 0), "127.0.0.1"), PvelSentence)
    assert gate.admit(pvel.encode(2, 0.5, 0), "127.0.0.3") is DropReason.NOT_HOLDER


def test_count_restarts_only_for_a_new_session() -> None:
    gate = VelocityGate(require_tag=True)
    gate.set_holder(Holder("s1", "127.0.0.1", KEY))
    assert isinstance(gate.admit(tagged(100), "127.0.0.1"), PvelSentence)
    gate.set_holder(None)
    gate.set_holder(Holder("s1", "127.0.0.1", KEY))
    # The same session re-engaging cannot have its old packets replayed.
    assert gate.admit(tagged(50), "127.0.0.1") is DropReason.OUT_OF_ORDER
    gate.set_holder(Holder("s2", "127.0.0.1", OTHER_KEY))
    assert isinstance(gate.admit(tagged(1, key=OTHER_KEY, sid="s2"), "127.0.0.1"), PvelSentence)


def test_ipv4_mapped_peers_match() -> None:
    assert normalize_host("::ffff:10.1.2.3") == "10.1.2.3"
    gate = VelocityGate(require_tag=True)
    gate.set_holder(Holder("s1", "::ffff:127.0.0.1", KEY))
    assert isinstance(gate.admit(tagged(1), "127.0.0.1"), PvelSentence)


# --------------------------------------------------------------------------- arbiter, manual clock


@dataclass
class _Timer:
    when: float
    callback: Callable[[], None]
    cancelled: bool = False

    def cancel(self) -> None:
        self.cancelled = True


@dataclass
class ManualTimers:
    """A clock and ``call_later`` that move only when the test says so."""

    now: float = 1000.0
    timers: list[_Timer] = field(default_factory=list)

    def clock(self) -> float:
        return self.now

    def call_later(self, delay: float, callback: Callable[[], None]) -> _Timer:
        timer = _Timer(self.now + delay, callback)
        self.timers.append(timer)
        return timer

    def advance(self, seconds: float) -> None:
        target = self.now + seconds
        while True:
            due = [t for t in self.timers if not t.cancelled and t.when <= target]
            if not due:
                break
            timer = min(due, key=lambda t: t.when)
            self.timers.remove(timer)
            self.now = timer.when
            timer.callback()
        self.now = target


@asynccontextmanager
async def arbiter_on(bus: Bus, timers: ManualTimers) -> AsyncIterator[MotionArbiter]:
    arbiter = MotionArbiter(bus, deadman=0.3, clock=timers.clock, call_later=timers.call_later)
    arbiter.start()
    try:
        yield arbiter
    finally:
        arbiter.remove_subscriptions()


def motor_log(bus: Bus) -> list[Velocity]:
    log: list[Velocity] = []
    bus.subscribe(topics.MOTOR_COMMAND, log.append)
    return log


async def test_autonomous_mode_obeys_cmd_vel_and_ignores_the_stream() -> None:
    bus, timers = Bus(), ManualTimers()
    bus.publish(topics.OVERRIDE_STATE, OverrideState(False))
    log = motor_log(bus)
    async with arbiter_on(bus, timers) as arbiter:
        assert arbiter.mode is Mode.AUTONOMOUS
        assert log == [STOP]
        bus.publish(topics.CMD_VEL, Velocity(0.4, 0.1))
        bus.publish(topics.TELEOP_VELOCITY, Velocity(1.0, 1.0))
        assert log == [STOP, Velocity(0.4, 0.1)]


async def test_teleop_obeys_the_stream_and_ignores_cmd_vel() -> None:
    bus, timers = Bus(), ManualTimers()
    log = motor_log(bus)
    async with arbiter_on(bus, timers) as arbiter:
        bus.publish(topics.CMD_VEL, Velocity(0.4, 0.0))
        bus.publish(topics.OVERRIDE_STATE, OverrideState(True, "s1", "st"))
        # The switch itself commands zero, inside the delivery of the override state.
        assert arbiter.mode is Mode.TELEOP
        assert log[-1] == STOP
        bus.publish(topics.CMD_VEL, Velocity(0.9, 0.0))
        bus.publish(topics.TELEOP_VELOCITY, Velocity(-0.5, 0.25))
        assert log == [STOP, Velocity(0.4, 0.0), STOP, Velocity(-0.5, 0.25)]
        bus.publish(topics.OVERRIDE_STATE, OverrideState(False))
        assert arbiter.mode is Mode.AUTONOMOUS
        assert log[-1] == STOP
        bus.publish(topics.TELEOP_VELOCITY, Velocity(-0.5, 0.25))
        assert log[-1] == STOP


async def test_deadman_zeroes_the_motors_until_the_next_valid_packet() -> None:
    bus, timers = Bus(), ManualTimers()
    log = motor_log(bus)
    async with arbiter_on(bus, timers) as arbiter:
        bus.publish(topics.OVERRIDE_STATE, OverrideState(True, "s1", "st"))
        assert arbiter.deadman_tripped  # nothing received yet: held at zero
        for _ in range(10):  # a healthy 20 Hz stream for half a second
            bus.publish(topics.TELEOP_VELOCITY, Velocity(0.6, 0.0))
            timers.advance(0.05)
        assert not arbiter.deadman_tripped
        assert log[-1] == Velocity(0.6, 0.0)
        timers.advance(0.24)  # 0.29 s of silence: still driving
        assert log[-1] == Velocity(0.6, 0.0)
        assert arbiter.deadman_trips == 0
        timers.advance(0.02)  # 0.31 s
        assert log[-1] == STOP
        assert arbiter.deadman_tripped
        assert arbiter.deadman_trips == 1
        timers.advance(5.0)
        assert log[-1] == STOP
        assert arbiter.deadman_trips == 1
        bus.publish(topics.TELEOP_VELOCITY, Velocity(0.2, 0.1))
        assert log[-1] == Velocity(0.2, 0.1)
        assert not arbiter.deadman_tripped
        assert bus.last(topics.MOTION_STATE) == arbiter.snapshot()
        timers.advance(0.31)
        assert log[-1] == STOP
        assert arbiter.deadman_trips == 2
        # The timer does not outlive teleop.
        bus.publish(topics.TELEOP_VELOCITY, Velocity(0.2, 0.1))
        bus.publish(topics.OVERRIDE_STATE, OverrideState(False))
        assert all(t.cancelled for t in timers.timers)


# --------------------------------------------------------------------------- over real sockets


async def test_stream_end_to_end_with_spoofs_and_session_loss(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(quiet_platform_config(), fleet_key)
    bus = daemon.bus
    commands = motor_log(bus)
    conn = await open_connection(daemon, fleet_key)
    good, spoof = udp_socket("127.0.0.1"), udp_socket("127.0.0.2")
    try:
        info = await conn.call("get_velocity_connection_info")
        assert info["auth"] == "hmac-sha256-64"
        assert info["port"] == daemon.ctx.velocity_port
        assert conn.capabilities["velocity"]["tag_bytes"] == 8
        target = (info["host"], info["port"])
        encoder = pvel.PvelEncoder(key=conn.session_key, session_id=conn.session_id)

        # Before the override: the stream moves nothing.
        good.sendto(encoder.encode(0.5, 0.0), target)
        stats = functools.partial(daemon.ctx.telemetry.build_one, VelocityLink)
        await wait_until(lambda: stats().dropped["not_engaged"] == 1)

        # Engaging is acknowledged only once the motors follow the stream (and are at zero).
        assert daemon.ctx.arming is not None  # disarmed at start (issue 27): armed for autonomy
        assert daemon.ctx.arming.arm("test") is None
        bus.publish(topics.CMD_VEL, Velocity(0.3, 0.0))
        assert commands[-1] == Velocity(0.3, 0.0)
        assert await conn.call("set_manual_override", engaged=True) is True
        motion = functools.partial(daemon.ctx.telemetry.build_one, Motion)
        assert motion().mode == "teleop"
        assert commands[-1] == STOP

        good.sendto(encoder.encode(0.5, -0.25), target)
        await wait_until(lambda: commands[-1] == Velocity(0.5, -0.25))
        bus.publish(topics.CMD_VEL, Velocity(0.9, 0.9))  # autonomy is ignored now
        assert commands[-1] == Velocity(0.5, -0.25)

        # A replay, a spoofed source (valid tag!), a forged tag: all dropped and counted.
        replay = encoder.encode(1.0, 1.0)
        good.sendto(replay, target)
        await wait_until(lambda: commands[-1] == Velocity(1.0, 1.0))
        good.sendto(replay, target)
        spoof.sendto(encoder.encode(-1.0, 0.0), target)
        good.sendto(
            pvel.encode(
                encoder.next_count + 5, -1.0, 0.0, key=os.urandom(32), session_id=conn.session_id
            ),
            target,
        )
        good.sendto(pvel.encode(encoder.next_count + 6, -1.0, 0.0), target)
        good.sendto(b"$PVEL,999999,0.1,0.1*00", target)
        await wait_until(
            lambda: (
                stats().dropped["out_of_order"] == 1
                and stats().dropped["not_holder"] == 1
                and stats().dropped["bad_tag"] == 2
                and stats().dropped["bad_checksum"] == 1
            )
        )
        assert commands[-1] == Velocity(1.0, 1.0)
        assert stats().accepted == 2

        # The counters reach the bus for telemetry.
        receiver = next(a for a in daemon.ctx.supervisor.actors if a.name == "velocity")
        receiver.publish_stats()  # type: ignore[attr-defined]
        published = bus.last(topics.VELOCITY_LINK_STATS)
        assert published is not None
        assert published.accepted == 2

        # The session ends: back to Autonomous Mode with the motors at zero.
        await conn.close()
        await wait_until(lambda: motion().mode == "autonomous")
        assert commands[-1] == STOP
        good.sendto(encoder.encode(0.5, 0.5), target)
        await wait_until(lambda: stats().dropped["not_engaged"] == 2)
        assert commands[-1] == STOP
    finally:
        good.close()
        spoof.close()
        await conn.close()


async def test_deadman_over_a_real_stream(platform_factory: Factory, fleet_key: bytes) -> None:
    daemon = await platform_factory(quiet_platform_config("velocity.deadman=0.1"), fleet_key)
    commands = motor_log(daemon.bus)
    conn = await open_connection(daemon, fleet_key)
    sock = udp_socket()
    try:
        assert await conn.call("set_manual_override", engaged=True) is True
        target = ("127.0.0.1", daemon.ctx.velocity_port)
        encoder = pvel.PvelEncoder(key=conn.session_key, session_id=conn.session_id)
        tripped = asyncio.Event()
        daemon.bus.subscribe(
            topics.MOTION_STATE, lambda state: tripped.set() if state.deadman else None
        )
        sock.sendto(encoder.encode(0.7, 0.0), target)
        await wait_until(lambda: commands[-1] == Velocity(0.7, 0.0))
        tripped.clear()
        await asyncio.wait_for(tripped.wait(), 5)  # the stream stopped: the deadman trips
        assert commands[-1] == STOP
        sock.sendto(encoder.encode(0.7, 0.0), target)
        await wait_until(lambda: commands[-1] == Velocity(0.7, 0.0))
        assert await conn.call("set_manual_override", engaged=False) is True
        assert commands[-1] == STOP
    finally:
        sock.close()
        await conn.close()


async def test_insecure_platform_accepts_untagged_from_the_holder_host(
    platform_factory: Factory,
) -> None:
    daemon = await platform_factory(quiet_platform_config(), None)
    commands = motor_log(daemon.bus)
    conn = await open_connection(daemon, None)
    good, spoof = udp_socket("127.0.0.1"), udp_socket("127.0.0.2")
    try:
        assert conn.capabilities["velocity"]["auth"] == "none"
        assert await conn.call("set_manual_override", engaged=True) is True
        target = ("127.0.0.1", daemon.ctx.velocity_port)
        spoof.sendto(pvel.encode(1, -1.0, 0.0), target)
        good.sendto(pvel.encode(2, 0.25, 0.0), target)
        await wait_until(lambda: commands[-1] == Velocity(0.25, 0.0))
        assert daemon.ctx.telemetry.build_one(VelocityLink).dropped["not_holder"] == 1
    finally:
        good.close()
        spoof.close()
        await conn.close()


async def test_session_timeout_returns_to_autonomous_while_packets_keep_coming(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    config = quiet_platform_config(
        "signaling.session_timeout=0.3",
        "signaling.heartbeat_interval=30",
        "failsafe.hold_after=0.2",
    )
    daemon = await platform_factory(config, fleet_key)
    commands = motor_log(daemon.bus)
    conn = await open_connection(daemon, fleet_key)
    sock = udp_socket()
    stats = functools.partial(daemon.ctx.telemetry.build_one, VelocityLink)
    try:
        assert await conn.call("set_manual_override", engaged=True) is True
        target = ("127.0.0.1", daemon.ctx.velocity_port)
        encoder = pvel.PvelEncoder(key=conn.session_key, session_id=conn.session_id)
        closed = asyncio.Event()
        daemon.bus.subscribe(topics.SESSION_CLOSED, lambda _event: closed.set())

        async def stale_station() -> None:
            # The station keeps streaming although its session is gone (it missed heartbeats).
            while True:
                sock.sendto(encoder.encode(0.8, 0.0), target)
                await asyncio.sleep(0.02)

        async with asyncio.TaskGroup() as group:
            streaming = group.create_task(stale_station())
            await wait_until(lambda: commands[-1] == Velocity(0.8, 0.0))
            await asyncio.wait_for(closed.wait(), 5)
            assert commands[-1] == STOP
            assert not daemon.bus.last(topics.OVERRIDE_STATE).engaged
            dropped = stats().dropped["not_engaged"]
            await wait_until(lambda: stats().dropped["not_engaged"] >= dropped + 3)
            assert commands[-1] == STOP
            streaming.cancel()
    finally:
        sock.close()
        await conn.close()
