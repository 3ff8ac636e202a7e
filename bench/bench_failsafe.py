"""The failsafe ladder (issue 13): link cut to motors at zero, and to hold, over 50 cuts.

An in-process platform, a station session on real sockets: each cycle sends a heartbeat and a
velocity datagram, then goes silent (the cut). Measured from the cut to the motion arbiter's
zero command (``velocity.deadman`` 300 ms) and to the ladder's hold (``failsafe.hold_after``,
set to 0.5 s here so 50 cuts take half a minute), with each figure's overshoot beyond its
configured time. The operator re-engages after each hold.

Then the replay figure (issue 19): during each of a few 3 s cuts, a third party replays the
station's captured ``$PVEL`` (genuine tags, the station's own address: loopback here) every
50 ms; the ladder must hold at ``failsafe.hold_after`` (its default, 1.5 s) all the same, within
50 ms, and when the link returns the station's fresh stream must not move the motors until the
operator re-engages.
"""

from __future__ import annotations

import asyncio
import socket
import time
from typing import Any

from bench.bench_velocity import _in_process_platform
from bench.support import percentiles
from brasidas import topics
from brasidas.codecs.pvel import PvelEncoder
from brasidas.messages import FailsafeState, FailsafeStep, Velocity

CUTS = 50
DEADMAN = 0.3
HOLD_AFTER = 0.5
REPLAY_CUTS = 5
REPLAY_CUT_S = 3.0
REPLAY_HOLD_AFTER = 1.5
"""failsafe.hold_after's default."""
REPLAY_INTERVAL = 0.05


async def run() -> dict[str, Any]:
    daemon, connection = await _in_process_platform(
        "motor.enabled=false",
        f"velocity.deadman={DEADMAN}",
        f"failsafe.hold_after={HOLD_AFTER}",
        "failsafe.release_after=60",
        "signaling.heartbeat_interval=600",  # the bench sends each heartbeat itself
        "signaling.session_timeout=600",
    )
    zero = asyncio.Event()
    hold = asyncio.Event()
    times: dict[str, float] = {}

    def on_motor(velocity: Velocity) -> None:
        if velocity == Velocity(0.0, 0.0) and "zero" not in times:
            times["zero"] = time.perf_counter()
            zero.set()

    def on_failsafe(state: FailsafeState) -> None:
        if state.step is FailsafeStep.HOLD:
            times["hold"] = time.perf_counter()
            hold.set()

    moving = asyncio.Event()
    unsubscribe = [
        daemon.bus.subscribe(topics.MOTOR_COMMAND, lambda v: moving.set() if v.linear else None),
        daemon.bus.subscribe(topics.MOTOR_COMMAND, on_motor),
        daemon.bus.subscribe(topics.FAILSAFE_STATE, on_failsafe),
    ]
    assert connection.session_key is not None
    encoder = PvelEncoder(key=connection.session_key, session_id=connection.session_id)
    target = ("127.0.0.1", daemon.ctx.velocity_port)
    to_zero: list[float] = []
    to_hold: list[float] = []
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for _ in range(CUTS):
            if not await connection.call("set_manual_override", engaged=True):
                raise RuntimeError("re-engage refused")
            moving.clear()
            sock.sendto(encoder.encode(0.5, 0.0), target)
            await asyncio.wait_for(moving.wait(), 5)
            times.clear()
            zero.clear()
            hold.clear()
            await connection.call("heartbeat")
            sock.sendto(encoder.encode(0.5, 0.0), target)
            cut = time.perf_counter()  # nothing more from the station: the link is cut
            await asyncio.wait_for(hold.wait(), 10)
            await asyncio.wait_for(zero.wait(), 1)
            to_zero.append((times["zero"] - cut) * 1000)
            to_hold.append((times["hold"] - cut) * 1000)
    finally:
        sock.close()
        for remove in unsubscribe:
            remove()
        await connection.close()
        await daemon.stop()
    figures: dict[str, Any] = {"cuts": CUTS, "deadman_ms": DEADMAN * 1000}
    figures["hold_after_ms"] = HOLD_AFTER * 1000
    for name, samples, configured in (
        ("cut_to_zero", to_zero, DEADMAN),
        ("cut_to_hold", to_hold, HOLD_AFTER),
    ):
        for key, value in percentiles(samples).items():
            figures[f"{name}_{key}_ms"] = value
        figures[f"{name}_overshoot_p99_ms"] = round(
            percentiles(samples)["p99"] - configured * 1000, 1
        )
    figures.update(await replay_during_cuts())
    return figures


async def replay_during_cuts() -> dict[str, Any]:
    """Hold time (from the station's last accepted word, on the session's clock) under a
    replay, and motor commands after the link returns, over :data:`REPLAY_CUTS` cuts of
    :data:`REPLAY_CUT_S`."""
    daemon, connection = await _in_process_platform(
        "motor.enabled=false",
        f"velocity.deadman={DEADMAN}",
        f"failsafe.hold_after={REPLAY_HOLD_AFTER}",
        "failsafe.release_after=60",
        "signaling.heartbeat_interval=600",
        "signaling.session_timeout=600",
    )
    holds: list[float] = []
    moved_after_restore = 0
    replayed = 0
    commands: list[tuple[float, Velocity]] = []
    steps: list[tuple[float, FailsafeStep]] = []
    unsubscribe = [
        daemon.bus.subscribe(
            topics.MOTOR_COMMAND, lambda v: commands.append((time.perf_counter(), v))
        ),
        daemon.bus.subscribe(
            topics.FAILSAFE_STATE, lambda s: steps.append((time.monotonic(), s.step))
        ),
    ]
    assert connection.session_key is not None
    encoder = PvelEncoder(key=connection.session_key, session_id=connection.session_id)
    target = ("127.0.0.1", daemon.ctx.velocity_port)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        for _ in range(REPLAY_CUTS):
            await connection.call("set_manual_override", engaged=True)
            captured = [encoder.encode(0.5, 0.0) for _ in range(20)]
            for datagram in captured:
                sock.sendto(datagram, target)
            await connection.call("heartbeat")
            sock.sendto(captured[-1], target)  # a duplicate: the replay starts at once
            session = daemon.ctx.sessions.sessions[connection.session_id]
            # The station's last word before the link goes, as the ladder sees it.
            cut = max(session.last_seen, session.last_velocity)
            steps.clear()
            deadline = time.perf_counter() + REPLAY_CUT_S
            index = 0
            while time.perf_counter() < deadline:
                sock.sendto(captured[index % len(captured)], target)
                index += 1
                replayed += 1
                await asyncio.sleep(REPLAY_INTERVAL)
            hold_at = next((at for at, step in steps if step is FailsafeStep.HOLD), None)
            holds.append(float("inf") if hold_at is None else (hold_at - cut) * 1000)
            # The link returns: heartbeats and a fresh stream, still 0.5 forward.
            restored = time.perf_counter()
            await connection.call("heartbeat")
            while time.perf_counter() < restored + 1.0:
                sock.sendto(encoder.encode(0.5, 0.0), target)
                await asyncio.sleep(REPLAY_INTERVAL)
            moved_after_restore += sum(
                1 for at, velocity in commands if at >= restored and velocity.linear != 0
            )
    finally:
        sock.close()
        for remove in unsubscribe:
            remove()
        await connection.close()
        await daemon.stop()
    configured_ms = REPLAY_HOLD_AFTER * 1000
    errors = [hold - configured_ms for hold in holds]
    return {
        "replay_cuts": REPLAY_CUTS,
        "replay_cut_s": REPLAY_CUT_S,
        "replay_datagrams": replayed,
        "replay_hold_after_ms": configured_ms,
        "replay_cut_to_hold_ms": [round(hold, 1) for hold in holds],
        "replay_hold_error_max_ms": round(max(abs(error) for error in errors), 1),
        "replay_hold_within_50_ms": all(abs(error) <= 50 for error in errors),
        "replay_motor_commands_after_restore": moved_after_restore,
    }
