"""Command authority and command age (issue 13), on loopback with real station daemons.

- ``movrd --force`` to the previous holder's 90.17 CONTROL TAKEN, over 30 alternating
  takeovers between two station daemons (heartbeats 30 s apart, telemetry every 5 s: the notice
  rides the telemetry the platform pushes when control changes hands);
- each velocity packet's age as the platform measures it (the station stamps ``$PVEL`` in the
  platform's clock, estimated from its heartbeats), over 10 s of 20 Hz teleop, with the
  station's clock estimate's error bound (half its quickest heartbeat round trip).
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import time
from collections.abc import AsyncIterator
from typing import Any

from bench.bench_velocity import _in_process_platform
from bench.support import free_port, percentiles
from brasidas import security, topics
from brasidas.config import StationConfig, load_config
from brasidas.messages import StationNotification
from platformd.velocity import VelocityReceiver
from stationd.daemon import StationDaemon
from stationd.telemetry import CONTROL_TAKEN

TAKEOVERS = 30
DRIVE_S = 10.0


@contextlib.asynccontextmanager
async def _station(key: bytes, name: str) -> AsyncIterator[StationDaemon]:
    config = load_config(
        StationConfig,
        None,
        [
            "station.api_port=0",
            f"discovery.port={free_port(socket.SOCK_DGRAM)}",
            "discovery.bind_host=127.0.0.1",
            f"station.id={name}",
            "telemetry.rate_hz=0.2",
            "telemetry.silence_s=60",
        ],
    )
    daemon = StationDaemon(config, key)
    await daemon.start()
    try:
        yield daemon
    finally:
        await daemon.stop()


async def run() -> dict[str, Any]:
    key = security.load_or_create_key(security.default_key_path())
    platform, bench_connection = await _in_process_platform(
        "motor.enabled=false", "signaling.heartbeat_interval=30", "signaling.session_timeout=120"
    )
    await bench_connection.close()  # the helper's own session: not a station of this bench
    pid, url = platform.config.platform.id, platform.ctx.signaling_url
    notices: list[float] = []
    answers: list[float] = []
    ages: list[float] = []
    try:
        async with _station(key, "alpha") as alpha, _station(key, "bravo") as bravo:
            stations = (alpha, bravo)
            told: dict[str, float] = {}
            for station in stations:
                await station.ctx.api.call_local("connect", platform_id=pid, url=url)
                name = station.config.station.id

                def on_note(note: StationNotification, name: str = name) -> None:
                    if note.code == CONTROL_TAKEN and note.active:
                        told.setdefault(name, time.perf_counter())

                station.bus.subscribe(topics.STATION_NOTIFICATIONS, on_note)
            await alpha.ctx.api.call_local("movrd", platform_id=pid, engaged=True)
            for i in range(TAKEOVERS):
                taker, loser = stations[(i + 1) % 2], stations[i % 2]
                told.clear()
                started = time.perf_counter()
                answer = await taker.ctx.api.call_local(
                    "movrd", platform_id=pid, engaged=True, force=True
                )
                answered = time.perf_counter()
                if not answer.get("accepted"):
                    raise RuntimeError(f"takeover refused: {answer}")
                deadline = started + 5
                while loser.config.station.id not in told:
                    if time.perf_counter() > deadline:
                        raise RuntimeError("no CONTROL TAKEN within 5 s")
                    await asyncio.sleep(0.001)
                notices.append((told[loser.config.station.id] - started) * 1000)
                answers.append((answered - started) * 1000)
                await asyncio.sleep(0.1)
            # The last taker drives: each packet's age as the platform measured it.
            driver = stations[TAKEOVERS % 2]
            receiver = next(
                a for a in platform.ctx.supervisor.actors if isinstance(a, VelocityReceiver)
            )

            def on_velocity(_velocity: object) -> None:
                if receiver.gate.last_age_ms is not None:
                    ages.append(receiver.gate.last_age_ms)

            remove = platform.bus.subscribe(topics.TELEOP_VELOCITY, on_velocity)
            end = time.monotonic() + DRIVE_S
            while time.monotonic() < end:
                await driver.ctx.api.call_local(
                    "teleop_set", platform_id=pid, linear=0.2, angular=0.0
                )
                await asyncio.sleep(0.1)
            remove()
            best = driver.ctx.connections[pid].clock_offset.best
            error_ms = None if best is None else round(best.round_trip * 500, 3)
    finally:
        await platform.stop()
    figures: dict[str, Any] = {"takeovers": len(notices)}
    for key_name, value in percentiles(notices).items():
        figures[f"force_to_control_taken_{key_name}_ms"] = value
    figures["force_answered_p50_ms"] = percentiles(answers)["p50"]
    figures["packets_aged"] = len(ages)
    if ages:
        for key_name, value in percentiles(ages).items():
            figures[f"command_age_{key_name}_ms"] = value
        figures["command_age_max_ms"] = round(max(ages), 3)
    figures["clock_estimate_error_bound_ms"] = error_ms
    return figures
