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
import contextlib
import socket
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

from bench.bench_velocity import _in_process_platform
from bench.support import percentiles
from brasidas import topics
from brasidas.bus import Topic
from brasidas.codecs.pvel import PvelEncoder
from brasidas.messages import FailsafeState, FailsafeStep, Velocity
from platformd.app import PlatformDaemon
from stationd.client import PlatformConnection

T = TypeVar("T")

CUTS = 50
DEADMAN = 0.3
HOLD_AFTER = 0.5
REPLAY_CUTS = 5
REPLAY_CUT_S = 3.0
REPLAY_HOLD_AFTER = 1.5
"""failsafe.hold_after's default."""
REPLAY_INTERVAL = 0.05


@dataclass
class LadderRig:
    """An in-process platform and an engaged-capable station session on real sockets."""

    daemon: PlatformDaemon
    connection: PlatformConnection
    encoder: PvelEncoder
    sock: socket.socket
    target: tuple[str, int]
    removers: list[Callable[[], None]] = field(default_factory=list)

    def subscribe(self, topic: Topic[T], callback: Callable[[T], None]) -> None:
        self.removers.append(self.daemon.bus.subscribe(topic, callback))

    def send(self, datagram: bytes) -> None:
        self.sock.sendto(datagram, self.target)


@contextlib.asynccontextmanager
async def ladder_rig(hold_after: float) -> AsyncIterator[LadderRig]:
    """The platform with ``failsafe.hold_after`` and the bench's own heartbeats; all of it
    stopped on exit."""
    daemon, connection = await _in_process_platform(
        "motor.enabled=false",
        f"velocity.deadman={DEADMAN}",
        f"failsafe.hold_after={hold_after}",
        "failsafe.release_after=60",
        "signaling.heartbeat_interval=600",  # the bench sends each heartbeat itself
        "signaling.session_timeout=600",
    )
    assert connection.session_key is not None
    rig = LadderRig(
        daemon,
        connection,
        PvelEncoder(key=connection.session_key, session_id=connection.session_id),
        socket.socket(socket.AF_INET, socket.SOCK_DGRAM),
        ("127.0.0.1", daemon.ctx.velocity_port),
    )
    try:
        yield rig
    finally:
        rig.sock.close()
        for remove in rig.removers:
            remove()
        await connection.close()
        await daemon.stop()


async def run() -> dict[str, Any]:
    async with ladder_rig(HOLD_AFTER) as rig:
        figures = await cuts(rig)
    async with ladder_rig(REPLAY_HOLD_AFTER) as rig:
        figures.update(await replay_during_cuts(rig))
    return figures


async def cuts(rig: LadderRig) -> dict[str, Any]:
    """Cut to zero and to hold over :data:`CUTS` plain cuts."""
    connection, encoder = rig.connection, rig.encoder
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
    rig.subscribe(topics.MOTOR_COMMAND, lambda v: moving.set() if v.linear else None)
    rig.subscribe(topics.MOTOR_COMMAND, on_motor)
    rig.subscribe(topics.FAILSAFE_STATE, on_failsafe)
    to_zero: list[float] = []
    to_hold: list[float] = []
    for _ in range(CUTS):
        await connection.call("set_manual_override", engaged=True)
        moving.clear()
        rig.send(encoder.encode(0.5, 0.0))
        await asyncio.wait_for(moving.wait(), 5)
        times.clear()
        zero.clear()
        hold.clear()
        await connection.call("heartbeat")
        rig.send(encoder.encode(0.5, 0.0))
        cut = time.perf_counter()  # nothing more from the station: the link is cut
        await asyncio.wait_for(hold.wait(), 10)
        await asyncio.wait_for(zero.wait(), 1)
        to_zero.append((times["zero"] - cut) * 1000)
        to_hold.append((times["hold"] - cut) * 1000)
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
    return figures


async def replay_during_cuts(rig: LadderRig) -> dict[str, Any]:
    """Hold time (from the station's last accepted word, on the session's clock) under a
    replay, and motor commands after the link returns, over :data:`REPLAY_CUTS` cuts of
    :data:`REPLAY_CUT_S`."""
    daemon, connection, encoder = rig.daemon, rig.connection, rig.encoder
    holds: list[float] = []
    moved_after_restore = 0
    replayed = 0
    commands: list[tuple[float, Velocity]] = []
    steps: list[tuple[float, FailsafeStep]] = []
    rig.subscribe(topics.MOTOR_COMMAND, lambda v: commands.append((time.perf_counter(), v)))
    rig.subscribe(topics.FAILSAFE_STATE, lambda s: steps.append((time.monotonic(), s.step)))
    for _ in range(REPLAY_CUTS):
        await connection.call("set_manual_override", engaged=True)
        captured = [encoder.encode(0.5, 0.0) for _ in range(20)]
        for datagram in captured:
            rig.send(datagram)
        await connection.call("heartbeat")
        rig.send(captured[-1])  # a duplicate: the replay starts at once
        session = daemon.ctx.sessions.sessions[connection.session_id]
        # The station's last word before the link goes, as the ladder sees it.
        cut = max(session.last_seen, session.last_velocity)
        steps.clear()
        deadline = time.perf_counter() + REPLAY_CUT_S
        index = 0
        while time.perf_counter() < deadline:
            rig.send(captured[index % len(captured)])
            index += 1
            replayed += 1
            await asyncio.sleep(REPLAY_INTERVAL)
        hold_at = next((at for at, step in steps if step is FailsafeStep.HOLD), None)
        holds.append(float("inf") if hold_at is None else (hold_at - cut) * 1000)
        # The link returns: heartbeats and a fresh stream, still 0.5 forward.
        restored = time.perf_counter()
        await connection.call("heartbeat")
        while time.perf_counter() < restored + 1.0:
            rig.send(encoder.encode(0.5, 0.0))
            await asyncio.sleep(REPLAY_INTERVAL)
        moved_after_restore += sum(
            1 for at, velocity in commands if at >= restored and velocity.linear != 0
        )
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
