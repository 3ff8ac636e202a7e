"""The failsafe ladder (issue 13) on real sockets: the station's heartbeats and velocity
stream are cut (the station sends none: its automatic heartbeats are set to once a minute)."""

from __future__ import annotations

import socket
import time
from collections.abc import Awaitable, Callable

from conftest import quiet_platform_config, velocities_dropped, wait_until

from brasidas import topics
from brasidas.codecs import pvel
from brasidas.messages import FailsafeState, FailsafeStep, Mode, OverrideState, Velocity
from platformd.app import PlatformDaemon
from platformd.failsafe import FailsafeLadder
from stationd.client import PlatformConnection

Factory = Callable[..., Awaitable[PlatformDaemon]]
STOP = Velocity(0.0, 0.0)


def ladder_config(*overrides: str) -> list[str]:
    return [
        "velocity.deadman=0.1",
        "signaling.heartbeat_interval=60",  # the test sends each heartbeat itself
        "signaling.session_timeout=60",
        *overrides,
    ]


def scaled_defaults(*overrides: str) -> list[str]:
    """The defaults' session timeout between hold and release (5 s, 1.5 s), scaled down; the
    test sends each heartbeat itself."""
    return [
        "velocity.deadman=0.1",
        "signaling.heartbeat_interval=60",
        "signaling.session_timeout=0.6",
        "failsafe.hold_after=0.3",
        *overrides,
    ]


async def engaged_station(daemon: PlatformDaemon, key: bytes) -> PlatformConnection:
    conn = PlatformConnection(
        daemon.config.platform.id, daemon.ctx.signaling_url, station_id="st-1", fleet_key=key
    )
    await conn.open()
    assert await conn.call("set_manual_override", engaged=True) is True
    return conn


async def test_stop_then_hold_then_release_and_no_old_command_after_the_link_returns(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(
        quiet_platform_config(
            *ladder_config("failsafe.hold_after=0.4", "failsafe.release_after=1.2")
        ),
        fleet_key,
    )
    events: list[tuple[float, str]] = []
    commands: list[Velocity] = []
    daemon.bus.subscribe(topics.MOTOR_COMMAND, commands.append)
    daemon.bus.subscribe(
        topics.MOTOR_COMMAND,
        lambda v: events.append((time.monotonic(), "zero")) if v == STOP else None,
    )
    daemon.bus.subscribe(
        topics.FAILSAFE_STATE, lambda s: events.append((time.monotonic(), s.step.value))
    )
    conn = await engaged_station(daemon, fleet_key)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    target = ("127.0.0.1", daemon.ctx.velocity_port)
    encoder = pvel.PvelEncoder(key=conn.session_key, session_id=conn.session_id)
    try:
        sock.sendto(encoder.encode(0.6, 0.0), target)
        await wait_until(lambda: commands[-1] == Velocity(0.6, 0.0))
        cut = time.monotonic()
        events.clear()
        # The link is cut: no velocity (deadman), no heartbeat (hold).
        await wait_until(lambda: any(step == "hold" for _, step in events))
        zero_at = next(at for at, step in events if step == "zero")
        hold_at = next(at for at, step in events if step == "hold")
        last_call = daemon.ctx.sessions.sessions[conn.session_id].last_seen
        assert cut < zero_at < hold_at
        assert hold_at - last_call >= 0.4
        assert commands[-1] == STOP
        # The link comes back with a burst of velocities sent during the loss: none moves it.
        await conn.call("heartbeat")
        burst = [encoder.encode(0.6, 0.0) for _ in range(10)]
        for datagram in burst:
            sock.sendto(datagram, target)
        await wait_until(lambda: velocities_dropped(daemon, "held") == len(burst))
        assert commands[-1] == STOP
        # The operator re-engages deliberately; the burst stays spent.
        assert await conn.call("set_manual_override", engaged=True) is True
        assert daemon.bus.last(topics.FAILSAFE_STATE) == FailsafeState(
            FailsafeStep.NORMAL, "st-1", "re-engaged by the operator"
        )
        sock.sendto(burst[-1], target)
        await wait_until(lambda: velocities_dropped(daemon, "out_of_order") >= 1)
        assert commands[-1] == STOP
        sock.sendto(encoder.encode(0.3, 0.0), target)
        await wait_until(lambda: commands[-1] == Velocity(0.3, 0.0))

        # Cut again, for good this time: hold, then release (action = release): autonomy.
        events.clear()
        await wait_until(lambda: any(step == "released" for _, step in events), timeout=10)
        released_at = next(at for at, step in events if step == "released")
        assert released_at - daemon.ctx.sessions.sessions[conn.session_id].last_seen >= 1.2
        assert daemon.bus.last(topics.OVERRIDE_STATE) == OverrideState(False)
        motion = daemon.bus.last(topics.MOTION_STATE)
        assert motion is not None
        assert motion.mode is Mode.AUTONOMOUS
        report = await conn.call("get_telemetry_report")
        assert report["failsafe"]["step"] == "released"
        assert "no heartbeat from st-1" in report["failsafe"]["reason"]
    finally:
        sock.close()
        await conn.close()


async def test_action_hold_keeps_holding_past_release_after(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    # The daemon's own ladder is set far off; this one runs on an injected clock.
    daemon = await platform_factory(
        quiet_platform_config(
            *ladder_config(
                "failsafe.hold_after=50", "failsafe.release_after=100", "failsafe.action=hold"
            )
        ),
        fleet_key,
    )
    conn = await engaged_station(daemon, fleet_key)
    try:
        ladder = FailsafeLadder(daemon.ctx, clock=lambda: 0.0)
        seen = daemon.ctx.sessions.sessions[conn.session_id].last_seen
        ladder.tick(seen + 49.9)
        assert ladder.state.step is FailsafeStep.NORMAL
        ladder.tick(seen + 50.0)
        assert ladder.state.step is FailsafeStep.HOLD
        motion = daemon.bus.last(topics.MOTION_STATE)
        assert motion is not None
        assert motion.command == STOP
        assert motion.mode is Mode.TELEOP
        ladder.tick(seen + 1000.0)
        assert ladder.state.step is FailsafeStep.HOLD
        override = daemon.bus.last(topics.OVERRIDE_STATE)
        assert override is not None
        assert override.engaged  # still held, not released
    finally:
        await conn.close()


async def test_the_holders_session_outlives_the_ladder_which_releases_then_it_ends(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    # The defaults' proportions (session_timeout 5 s, hold 1.5 s, release 10 s), scaled down:
    # the session's timeout comes between hold and release, and must not pre-empt the release.
    daemon = await platform_factory(
        quiet_platform_config(*scaled_defaults("failsafe.release_after=1.2")), fleet_key
    )
    events: list[str] = []
    daemon.bus.subscribe(topics.FAILSAFE_STATE, lambda s: events.append(s.step.value))
    daemon.bus.subscribe(topics.SESSION_CLOSED, lambda e: events.append(f"closed: {e.reason}"))
    conn = await engaged_station(daemon, fleet_key)
    try:
        await wait_until(lambda: any(e.startswith("closed") for e in events), timeout=10)
        # The ladder's release step, then (silent past its timeout, no longer holding) the end.
        assert events[-3:] == ["hold", "released", "closed: timeout"]
        assert daemon.bus.last(topics.OVERRIDE_STATE) == OverrideState(False)
    finally:
        await conn.close()


async def test_with_action_hold_the_silent_holder_keeps_its_session_and_re_engages(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(
        quiet_platform_config(
            *scaled_defaults("failsafe.release_after=0.8", "failsafe.action=hold")
        ),
        fleet_key,
    )
    commands: list[Velocity] = []
    daemon.bus.subscribe(topics.MOTOR_COMMAND, commands.append)
    conn = await engaged_station(daemon, fleet_key)
    opened = daemon.ctx.sessions.sessions[conn.session_id]
    try:
        await wait_until(
            lambda: (
                (s := daemon.bus.last(topics.FAILSAFE_STATE)) is not None
                and s.step is FailsafeStep.HOLD
            )
        )
        # Well past session_timeout and release_after: still holding, the session still open.
        await wait_until(lambda: time.monotonic() - opened.last_seen > 1.5)
        assert conn.session_id in daemon.ctx.sessions.sessions
        override = daemon.bus.last(topics.OVERRIDE_STATE)
        assert override is not None
        assert override.engaged
        assert override.station_id == "st-1"
        assert daemon.bus.last(topics.FAILSAFE_STATE).step is FailsafeStep.HOLD  # type: ignore[union-attr]
        # The link returns: the same session, and the operator re-engages deliberately.
        await conn.call("heartbeat")
        assert await conn.call("set_manual_override", engaged=True) is True
        encoder = pvel.PvelEncoder(key=conn.session_key, session_id=conn.session_id)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.sendto(encoder.encode(0.4, 0.0), ("127.0.0.1", daemon.ctx.velocity_port))
            await wait_until(lambda: bool(commands) and commands[-1] == Velocity(0.4, 0.0))
    finally:
        await conn.close()


async def test_replayed_velocity_never_holds_off_the_ladder(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    """Issue 19, item 1: while the holder is silent, its captured packets replayed from its
    own address (duplicates, stale, held) are dropped and counted, and none counts as life:
    the ladder holds on time and stays held."""
    daemon = await platform_factory(
        quiet_platform_config(*ladder_config("failsafe.hold_after=0.4")), fleet_key
    )
    steps: list[tuple[float, str]] = []
    commands: list[Velocity] = []
    daemon.bus.subscribe(topics.MOTOR_COMMAND, commands.append)
    daemon.bus.subscribe(
        topics.FAILSAFE_STATE, lambda s: steps.append((time.monotonic(), s.step.value))
    )
    conn = await engaged_station(daemon, fleet_key)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    target = ("127.0.0.1", daemon.ctx.velocity_port)
    encoder = pvel.PvelEncoder(key=conn.session_key, session_id=conn.session_id)
    captured = [encoder.encode(0.5, 0.0) for _ in range(5)]
    try:
        for datagram in captured:
            sock.sendto(datagram, target)
        await wait_until(lambda: Velocity(0.5, 0.0) in commands)
        session = daemon.ctx.sessions.sessions[conn.session_id]
        last_life = max(session.last_seen, session.last_velocity)
        replayed = 0

        def held() -> bool:
            nonlocal replayed
            for datagram in captured:  # the attacker's loop: every 10 ms, as fast as polled
                sock.sendto(datagram, target)
                replayed += 1
            return any(step == "hold" for _, step in steps)

        await wait_until(held, timeout=5)
        hold_at = next(at for at, step in steps if step == "hold")
        assert hold_at - last_life >= 0.4
        assert max(session.last_seen, session.last_velocity) == last_life
        # The replays go on after the hold: counted as held, and nothing moves.
        for datagram in captured:
            sock.sendto(datagram, target)
            replayed += 1
        await wait_until(
            lambda: (
                velocities_dropped(daemon, "out_of_order") + velocities_dropped(daemon, "held")
                == replayed
            )
        )
        assert commands[-1] == STOP
        failsafe = daemon.bus.last(topics.FAILSAFE_STATE)
        assert failsafe is not None
        assert failsafe.step is FailsafeStep.HOLD
    finally:
        sock.close()
        await conn.close()
