"""The latency-following speed cap (issue 13, R-11.5): derivation, and the motors on a real
stream never above it."""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Awaitable, Callable

from conftest import quiet_platform_config, wait_until

from brasidas import topics
from brasidas.codecs import pvel
from brasidas.config.platform import SafetySection
from brasidas.messages import Velocity
from platformd.app import PlatformDaemon
from platformd.speedcap import compute_cap, stopping_speed
from stationd.client import PlatformConnection

Factory = Callable[..., Awaitable[PlatformDaemon]]


def test_the_seeds_budget_is_the_derivation() -> None:
    # 250 ms reaction + 150 ms video at 6 km/h stops within 1 m with the default braking.
    safety = SafetySection()
    speed = stopping_speed(safety.stop_distance_m, 0.25, 0.150, safety.braking_mps2)
    assert 5.9 < speed * 3.6 < 6.1
    fast, slow = compute_cap(safety, 6.0, 50, 0), compute_cap(safety, 6.0, 400, 0)
    assert fast.cap_kmh > slow.cap_kmh
    assert fast.cap_kmh == 6.0  # the platform's own limit
    assert slow.cap_kmh < 5.0
    assert "stops within 1 m" in slow.reason
    unknown = compute_cap(safety, 6.0, None, None)
    assert unknown.cap_kmh == compute_cap(safety, 6.0, safety.worst_latency_ms, 0).cap_kmh
    assert unknown.reason.startswith("no latency report")
    # Whatever the latency, the stopping distance at the cap is the configured one at most.
    for latency_ms in (0, 100, 250, 400, 1000):
        cap = compute_cap(safety, 100.0, latency_ms, 0)
        v = cap.cap_kmh / 3.6
        dead = safety.reaction_s + latency_ms / 1000
        assert dead * v + v * v / (2 * safety.braking_mps2) <= safety.stop_distance_m + 1e-9


async def test_motors_follow_the_reported_latency_and_never_exceed_the_cap(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(quiet_platform_config("safety.worst_latency_ms=400"), fleet_key)
    commands: list[Velocity] = []
    daemon.bus.subscribe(topics.MOTOR_COMMAND, commands.append)
    conn = PlatformConnection(
        daemon.config.platform.id, daemon.ctx.signaling_url, station_id="st-1", fleet_key=fleet_key
    )
    await conn.open()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    target = ("127.0.0.1", daemon.ctx.velocity_port)
    try:
        assert await conn.call("set_manual_override", engaged=True) is True
        encoder = pvel.PvelEncoder(key=conn.session_key, session_id=conn.session_id)
        report = await conn.call("get_telemetry_report")
        assert report["speed_cap"]["reason"].startswith("no latency report")
        slow = await conn.call("report_latency", video_ms=400.0, command_ms=0.0)
        fast_cap = (await conn.call("report_latency", video_ms=50.0, command_ms=0.0))["cap_kmh"]
        assert fast_cap > slow["cap_kmh"]
        await conn.call("report_latency", video_ms=400.0, command_ms=0.0)
        cap = daemon.bus.last(topics.SPEED_CAP)
        assert cap is not None
        assert cap.video_ms == 400.0
        fraction = cap.fraction
        assert abs(fraction * daemon.config.platform.max_speed_kmh - slow["cap_kmh"]) < 0.01
        sock.sendto(encoder.encode(1.0, 0.5), target)
        await wait_until(lambda: bool(commands) and commands[-1].linear > 0)
        assert commands[-1] == Velocity(fraction, 0.5)
        sock.sendto(encoder.encode(-1.0, 0.0), target)
        await wait_until(lambda: commands[-1].linear < 0)
        assert commands[-1].linear == -fraction
        # A lower latency raises the cap: full speed is allowed again.
        await conn.call("report_latency", video_ms=50.0, command_ms=0.0)
        sock.sendto(encoder.encode(1.0, 0.0), target)
        await wait_until(lambda: commands[-1].linear == 1.0)
        report = await conn.call("get_telemetry_report")
        assert report["speed_cap"]["video_ms"] == 50.0
        assert max(abs(c.linear) for c in commands[:-1]) <= fraction + 1e-9
    finally:
        sock.close()
        await conn.close()


async def test_the_holders_station_reports_its_video_latency_with_each_heartbeat(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(
        quiet_platform_config("signaling.heartbeat_interval=0.1"), fleet_key
    )
    conn = PlatformConnection(
        daemon.config.platform.id, daemon.ctx.signaling_url, station_id="st-1", fleet_key=fleet_key
    )
    conn.video_latency = lambda: 300.0
    await conn.open()
    try:
        await asyncio.sleep(0.3)  # heartbeats without the override report nothing
        cap = daemon.bus.last(topics.SPEED_CAP)
        assert cap is not None
        assert cap.video_ms is None
        assert await conn.call("set_manual_override", engaged=True) is True
        await wait_until(lambda: _video_ms(daemon) == 300.0)
        cap = daemon.bus.last(topics.SPEED_CAP)
        assert cap is not None
        assert cap.command_ms is not None
        assert cap.cap_kmh < 6.0
    finally:
        await conn.close()


def _video_ms(daemon: PlatformDaemon) -> float | None:
    cap = daemon.bus.last(topics.SPEED_CAP)
    return cap.video_ms if cap is not None else None


async def test_a_picture_freezing_between_heartbeats_is_reported_before_the_next(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    """Heartbeats 3 s apart: the frozen picture's age reaches the cap within a second."""
    daemon = await platform_factory(
        quiet_platform_config("signaling.heartbeat_interval=3"), fleet_key
    )
    conn = PlatformConnection(
        daemon.config.platform.id, daemon.ctx.signaling_url, station_id="st-1", fleet_key=fleet_key
    )
    picture_age = [20.0]
    conn.video_latency = lambda: picture_age[0]
    await conn.open()
    try:
        assert await conn.call("set_manual_override", engaged=True) is True
        await wait_until(lambda: _video_ms(daemon) == 20.0, timeout=5)  # a heartbeat's report
        picture_age[0] = 600.0  # the picture froze just after that heartbeat
        frozen_at = asyncio.get_running_loop().time()
        await wait_until(lambda: (_video_ms(daemon) or 0) >= 600.0, timeout=1.0)
        assert asyncio.get_running_loop().time() - frozen_at < 1.0
        cap = daemon.bus.last(topics.SPEED_CAP)
        assert cap is not None
        config = daemon.config
        worst = compute_cap(config.safety, config.platform.max_speed_kmh, None, None)
        assert cap.cap_kmh <= worst.cap_kmh  # the worst case's speed, or slower
        picture_age[0] = 650.0  # still frozen, only 50 ms older: no report before its heartbeat
        await asyncio.sleep(0.3)
        assert _video_ms(daemon) == 600.0
    finally:
        await conn.close()
