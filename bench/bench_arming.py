"""Stop for everyone and pre-arm (issue 27), on loopback with an in-process platform.

- a station *observer* (its session holds no control) sends ``stop`` over signaling's
  WebSocket while the controller drives: the call → the motion arbiter's zero on
  ``MOTOR_COMMAND`` (what the motor driver obeys), p50/p99 (target p99 ≤ 50 ms);
- a *signed* ground station that does not hold control sends a force-disarm
  (``MAV_CMD_COMPONENT_ARM_DISARM`` 0, 21196): the datagram sent → the same zero;
- what one pre-arm evaluation costs (the checks on the live bus state, and the pure function).

``BRASIDAS_BENCH_STOPS`` (default 50) sets how many stops each row measures.
"""

from __future__ import annotations

import asyncio
import hashlib
import os
import socket
import time
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bench.bench_velocity import _in_process_platform
from bench.support import percentiles
from brasidas import security, topics
from brasidas.messages import ImuStatus, Velocity
from platformd.app import PlatformDaemon
from platformd.arming import CLOCK_SET_AFTER, PrearmInputs, prearm_reasons
from stationd.client import PlatformConnection

STOPS = int(os.environ.get("BRASIDAS_BENCH_STOPS", "50"))
PASSPHRASE = "bench-signing-passphrase"
MOVING = Velocity(0.4, 0.0)


class _ZeroWatch:
    """When the arbiter next commands zero after ``arm()``."""

    def __init__(self, daemon: PlatformDaemon) -> None:
        self.at: float | None = None
        self._armed = False
        daemon.bus.subscribe(topics.MOTOR_COMMAND, self._on_command)

    def arm(self) -> None:
        self.at, self._armed = None, True

    def _on_command(self, velocity: Velocity) -> None:
        if self._armed and velocity == Velocity(0.0, 0.0):
            self.at, self._armed = time.perf_counter(), False

    async def wait(self, timeout: float = 2.0) -> float:
        deadline = time.perf_counter() + timeout
        while self.at is None:
            if time.perf_counter() > deadline:
                raise TimeoutError("no zero on MOTOR_COMMAND")
            await asyncio.sleep(0.0005)
        return self.at


async def _moving(daemon: PlatformDaemon, controller: PlatformConnection) -> None:
    """Armed, the override engaged, a non-zero command on the motors."""
    arming = daemon.ctx.arming
    assert arming is not None
    if not arming.armed:
        await controller.call("arm")
    daemon.bus.publish(topics.TELEOP_VELOCITY, MOVING)
    motion = daemon.bus.last(topics.MOTION_STATE)
    if motion is None or motion.command != MOVING:
        raise RuntimeError(f"not moving: {motion}")


async def _observer_stops() -> dict[str, Any]:
    daemon, controller = await _in_process_platform("motor.enabled=false")
    key = security.load_or_create_key(security.default_key_path())
    observer = PlatformConnection(
        daemon.config.platform.id, daemon.ctx.signaling_url, station_id="observer", fleet_key=key
    )
    await observer.open()
    watch = _ZeroWatch(daemon)
    samples: list[float] = []
    try:
        for _ in range(STOPS):
            await _moving(daemon, controller)
            watch.arm()
            sent = time.perf_counter()
            await observer.call("stop")
            samples.append((await watch.wait() - sent) * 1000)
    finally:
        await observer.close()
        await controller.close()
        await daemon.stop()
    return {f"observer_stop_to_zero_{k}_ms": v for k, v in percentiles(samples).items()}


async def _gcs_stops(state: Path) -> dict[str, Any]:
    key_file = state / "mavlink.pass"
    key_file.write_text(PASSPHRASE + "\n")
    key_file.chmod(0o600)
    daemon, controller = await _in_process_platform(
        "motor.enabled=false",
        "mavlink.enabled=true",
        "mavlink.targets=[]",
        "mavlink.port=0",
        f"mavlink.signing_key_file={key_file}",
    )
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    mav = mavlink.MAVLink(None, 254, 190)
    mav.signing.secret_key = hashlib.sha256(PASSPHRASE.encode()).digest()
    mav.signing.sign_outgoing = True
    mav.signing.link_id = 1
    mav.signing.timestamp = int((time.time() - 1420070400) * 100_000)
    vehicle = ("127.0.0.1", daemon.ctx.mavlink_port)
    watch = _ZeroWatch(daemon)
    samples: list[float] = []
    try:
        for _ in range(STOPS):
            await _moving(daemon, controller)
            watch.arm()
            frame = mavlink.MAVLink_command_long_message(
                1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 21196, 0, 0, 0, 0, 0
            ).pack(mav)
            mav.seq = (mav.seq + 1) % 256
            sent = time.perf_counter()
            sock.sendto(frame, vehicle)
            samples.append((await watch.wait() - sent) * 1000)
            while True:  # drain the answers
                try:
                    sock.recv(65536)
                except BlockingIOError:
                    break
    finally:
        sock.close()
        await controller.close()
        await daemon.stop()
    return {f"signed_gcs_stop_to_zero_{k}_ms": v for k, v in percentiles(samples).items()}


async def _prearm_cost() -> dict[str, Any]:
    daemon, controller = await _in_process_platform("motor.enabled=false")
    arming = daemon.ctx.arming
    assert arming is not None
    try:
        rounds = 20_000
        started = time.perf_counter()
        for _ in range(rounds):
            arming.reasons()
        live_us = (time.perf_counter() - started) / rounds * 1e6
    finally:
        await controller.close()
        await daemon.stop()
    inputs = PrearmInputs(
        now=10.0,
        wall=CLOCK_SET_AFTER + 1,
        gps_enabled=True,
        fix_age_s=0.1,
        imu_enabled=True,
        imu=ImuStatus(True),
        imu_age_s=0.2,
        up_s=10.0,
    )
    started = time.perf_counter()
    for _ in range(100_000):
        prearm_reasons(inputs)
    pure_us = (time.perf_counter() - started) / 100_000 * 1e6
    return {"prearm_live_us": round(live_us, 2), "prearm_pure_us": round(pure_us, 3)}


async def run() -> dict[str, Any]:
    state = Path(os.environ.get("XDG_STATE_HOME", "/tmp")) / "bench-arming"
    state.mkdir(parents=True, exist_ok=True)
    figures: dict[str, Any] = {"stops": STOPS, "loadavg": os.getloadavg()}
    figures |= await _observer_stops()
    figures |= await _gcs_stops(state)
    figures |= await _prearm_cost()
    return figures
