"""Each velocity packet's age (issue 13, item 5): the station stamps ``$PVEL`` with the send
time in the platform's clock, estimated from its heartbeats; the platform ages every packet on
arrival, caps the speed by the age and drops stale ones. Real sockets; the station's clock is
offset from the platform's by 5000 s (different hosts' monotonic clocks are unrelated)."""

from __future__ import annotations

import asyncio
import socket
import time
from collections.abc import AsyncIterator, Awaitable, Callable

import pytest
from conftest import quiet_platform_config, wait_until

from brasidas import topics
from brasidas.codecs import pvel
from brasidas.messages import CommandAge, Velocity
from platformd.app import PlatformDaemon
from platformd.speedcap import compute_cap
from stationd.client import ClockOffset, PlatformConnection

Factory = Callable[..., Awaitable[PlatformDaemon]]
STATION_AHEAD = 5000.0
"""The station's clock minus the platform's (s)."""


def station_clock() -> float:
    return time.monotonic() + STATION_AHEAD


def test_the_offset_is_the_quickest_round_trips_and_within_half_of_it() -> None:
    offset = ClockOffset(keep=4)
    assert offset.best is None
    # True offset -10 s. A symmetric 20 ms round trip, then one delayed 300 ms on the way back
    # (its sample is skewed by 150 ms), then a quick 2 ms one asymmetric by 1 ms.
    offset.add(sent=100.0, platform=90.010, received=100.020)
    offset.add(sent=101.0, platform=91.010, received=101.320)
    best = offset.best
    assert best is not None
    assert best.offset == pytest.approx(-10.0)
    assert best.round_trip == pytest.approx(0.02)
    offset.add(sent=102.0, platform=92.0015, received=102.002)
    best = offset.best
    assert best is not None
    assert best.round_trip == pytest.approx(0.002)
    assert abs(best.offset + 10.0) <= best.round_trip / 2
    # Old samples leave: only the last ``keep`` count.
    for i in range(4):
        offset.add(sent=200.0 + i, platform=190.05 + i, received=200.1 + i)
    best = offset.best
    assert best is not None
    assert best.round_trip == pytest.approx(0.1)


def test_a_queue_on_the_way_back_only_does_not_skew_the_offset_for_minutes() -> None:
    offset = ClockOffset()
    # True offset -10 s; a clean 2 ms round trip, then every answer held 200 ms in a queue
    # platform → station (the video filling the link), one a second for three minutes.
    offset.add(sent=100.0, platform=90.001, received=100.002)
    for i in range(1, 180):
        offset.add(sent=100.0 + i, platform=90.0 + i + 0.001, received=100.0 + i + 0.202)
    best = offset.best
    assert best is not None
    # Its skew (half the queue, 100 ms) would age every fresh command by 100 ms.
    assert abs(best.offset + 10.0) < 0.002
    assert best.error_bound(280.0) < 0.1
    # Long enough, the clocks' possible drift outweighs the quick sample's precision.
    for i in range(180, 600):
        offset.add(sent=100.0 + i, platform=90.0 + i + 0.001, received=100.0 + i + 0.202)
    best = offset.best
    assert best is not None
    assert best.round_trip == pytest.approx(0.202)


@pytest.fixture
async def driving(
    platform_factory: Factory, fleet_key: bytes
) -> AsyncIterator[tuple[PlatformDaemon, PlatformConnection]]:
    daemon = await platform_factory(
        quiet_platform_config(
            "signaling.heartbeat_interval=0.1",
            "velocity.max_age_ms=500",
            "velocity.deadman=0.1",
        ),
        fleet_key,
    )
    conn = PlatformConnection(
        daemon.config.platform.id,
        daemon.ctx.signaling_url,
        station_id="st-1",
        fleet_key=fleet_key,
        clock=station_clock,
    )
    await conn.open()
    try:
        await wait_until(lambda: len(conn.clock_offset.samples) >= 3)
        assert await conn.call("set_manual_override", engaged=True) is True
        yield daemon, conn
    finally:
        await conn.close()


def error_ms(conn: PlatformConnection) -> float:
    """How far the station's estimate of the platform's clock may be off (ms): half the
    round trip it was measured over (1 ms more for the stamp's rounding)."""
    best = conn.clock_offset.best
    assert best is not None
    return best.round_trip * 500 + 1


def command_age(daemon: PlatformDaemon) -> CommandAge | None:
    return daemon.bus.last(topics.COMMAND_AGE)


async def test_a_delayed_packet_is_aged_by_the_platform_across_offset_clocks(
    driving: tuple[PlatformDaemon, PlatformConnection],
) -> None:
    daemon, conn = driving
    best = conn.clock_offset.best
    assert best is not None
    assert abs(best.offset + STATION_AHEAD) <= best.round_trip / 2 + 0.001
    encoder = pvel.PvelEncoder(key=conn.session_key, session_id=conn.session_id)
    target = ("127.0.0.1", daemon.ctx.velocity_port)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.sendto(encoder.encode(0.1, 0.0, conn.platform_time_ms()), target)
        await wait_until(lambda: command_age(daemon) is not None)
        age = command_age(daemon)
        assert age is not None
        assert age.last_ms < 200  # loopback: at once (but a loaded machine)
        # A packet held back 250 ms on its way (a congested link) arrives 250 ms old.
        held = encoder.encode(0.1, 0.0, conn.platform_time_ms())
        await asyncio.sleep(0.25)
        sock.sendto(held, target)
        await wait_until(lambda: (a := command_age(daemon)) is not None and a.last_ms >= 200)
        age = command_age(daemon)
        # (Not 5000 s: the clocks' offset is accounted for, within half the quickest round
        # trip; transit on a loaded loopback adds milliseconds, seldom more.)
        assert age is not None
        assert 250 - error_ms(conn) <= age.last_ms < 1000
        assert age.max_ms == age.last_ms
        report = await conn.call("get_telemetry_report")
        assert report["velocity_link"]["age_ms"] == pytest.approx(age.last_ms, abs=0.1)
        assert report["speed_cap"]["command_ms"] == pytest.approx(age.max_ms, abs=0.1)


async def test_the_cap_follows_the_command_age_and_the_motors_never_exceed_it(
    driving: tuple[PlatformDaemon, PlatformConnection],
) -> None:
    daemon, conn = driving
    safety, max_kmh = daemon.config.safety, daemon.config.platform.max_speed_kmh
    commands: list[Velocity] = []
    daemon.bus.subscribe(topics.MOTOR_COMMAND, commands.append)
    # The station reports 50 ms of video latency and a (stale) half round trip of 0 ms: the
    # platform's own measurement of the packets' age is what counts.
    await conn.call("report_latency", video_ms=50.0, command_ms=0.0)
    encoder = pvel.PvelEncoder(key=conn.session_key, session_id=conn.session_id)
    target = ("127.0.0.1", daemon.ctx.velocity_port)

    def sent(age_ms: float) -> int:
        now = conn.platform_time_ms()
        assert now is not None
        return round(now - age_ms)

    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.sendto(encoder.encode(1.0, 0.0, sent(0)), target)
        await wait_until(lambda: bool(commands) and commands[-1].linear > 0)
        fresh = daemon.bus.last(topics.SPEED_CAP)
        assert fresh is not None
        assert fresh.command_ms is not None
        assert fresh.command_ms < 200
        assert "command age" in fresh.reason
        # Packets 300 ms old (a lag): the cap drops at once, before the packet moves anything.
        before = len(commands)
        sock.sendto(encoder.encode(1.0, 0.0, sent(300)), target)
        await wait_until(
            lambda: (
                (c := daemon.bus.last(topics.SPEED_CAP)) is not None
                and c.command_ms is not None
                and c.command_ms >= 300 - error_ms(conn)
            )
        )
        lagging = daemon.bus.last(topics.SPEED_CAP)
        assert lagging is not None
        assert lagging.command_ms is not None
        expected = compute_cap(safety, max_kmh, 50.0, lagging.command_ms)
        assert lagging.cap_kmh == pytest.approx(expected.cap_kmh)
        assert lagging.cap_kmh < fresh.cap_kmh
        moved = [c for c in commands[before:] if c.linear > 0]  # (then the deadman's zeros)
        assert moved
        assert moved[0].linear == pytest.approx(lagging.fraction)

        # Fresh packets again: once the old one leaves the window (1 s) the cap rises back.
        async def stream() -> None:
            while True:
                sock.sendto(encoder.encode(1.0, 0.0, sent(0)), target)
                await asyncio.sleep(0.05)

        streaming = asyncio.create_task(stream())
        try:
            await wait_until(
                lambda: (
                    (c := daemon.bus.last(topics.SPEED_CAP)) is not None
                    and c.command_ms is not None
                    and c.command_ms < 200
                ),
                timeout=15,
            )
        finally:
            streaming.cancel()
        # Each motor command was clamped to the cap of its packet's age, never above it.
        assert all(abs(c.linear) <= fresh.fraction + 1e-9 for c in commands)
        assert any(c.linear == pytest.approx(lagging.fraction) for c in commands)


async def test_a_burst_of_stale_commands_after_a_lag_spike_moves_nothing(
    driving: tuple[PlatformDaemon, PlatformConnection],
) -> None:
    daemon, conn = driving
    commands: list[Velocity] = []
    daemon.bus.subscribe(topics.MOTOR_COMMAND, commands.append)
    encoder = pvel.PvelEncoder(key=conn.session_key, session_id=conn.session_id)
    target = ("127.0.0.1", daemon.ctx.velocity_port)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        # Ten commands queue up behind a 600 ms lag spike, then arrive all at once.
        burst = []
        for _ in range(10):
            burst.append(encoder.encode(0.8, 0.3, conn.platform_time_ms()))
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.6)
        for datagram in burst:
            sock.sendto(datagram, target)

        async def stale() -> int:
            report = await conn.call("get_telemetry_report")
            return int(report["velocity_link"]["dropped"]["stale"])

        deadline = time.monotonic() + 5
        while await stale() < 10 and time.monotonic() < deadline:
            await asyncio.sleep(0.02)
        assert await stale() == 10
        assert all(c == Velocity(0.0, 0.0) for c in commands)  # nothing moved
        assert command_age(daemon) is None  # a dropped packet is no command latency
        # The link is back: the next fresh command moves the robot.
        sock.sendto(encoder.encode(0.8, 0.3, conn.platform_time_ms()), target)
        await wait_until(lambda: bool(commands) and commands[-1].linear > 0)
