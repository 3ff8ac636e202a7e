"""The turret payload (issue 13): trigger command to the microcontroller's acknowledgement.

The real driver (pyserial-asyncio) against the simulated microcontroller on a pty: ``FIRE`` and
``SAFE`` alternately, each timed from the call to the acknowledgement, 200 of each.
"""

from __future__ import annotations

import asyncio
import time
from typing import Any

import serial_asyncio

from bench.support import percentiles
from platformd.payloads.turret import TurretDriver
from platformd.sim.turret import TurretDevice, TurretSimulator

SAMPLES = 200


async def run() -> dict[str, Any]:
    simulator = TurretSimulator(TurretDevice(watchdog_s=5.0))
    simulator.start()
    transport, driver = await serial_asyncio.create_serial_connection(
        asyncio.get_running_loop(),
        lambda: TurretDriver(ack_timeout=0.5),
        simulator.path,
        baudrate=115200,
    )
    fire: list[float] = []
    safe: list[float] = []
    try:
        for _ in range(SAMPLES):
            for name, samples in (("FIRE", fire), ("SAFE", safe)):
                started = time.perf_counter()
                await driver.send(name)
                samples.append((time.perf_counter() - started) * 1000)
    finally:
        transport.close()
        simulator.close()
    figures: dict[str, Any] = {"samples": SAMPLES, "resent": driver.counters["resent"]}
    for name, samples in (("fire_to_ack", fire), ("safe_to_ack", safe)):
        for key, value in percentiles(samples).items():
            figures[f"{name}_{key}_ms"] = value
    return figures
