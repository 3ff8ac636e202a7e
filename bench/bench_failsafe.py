"""The failsafe ladder (issue 13): link cut to motors at zero, and to hold, over 50 cuts.

An in-process platform, a station session on real sockets: each cycle sends a heartbeat and a
velocity datagram, then goes silent (the cut). Measured from the cut to the motion arbiter's
zero command (``velocity.deadman`` 300 ms) and to the ladder's hold (``failsafe.hold_after``,
set to 0.5 s here so 50 cuts take half a minute), with each figure's overshoot beyond its
configured time. The operator re-engages after each hold.
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
    return figures
