"""``brasidas-platform simulate vehicle``: the simulated rover's serial devices, standalone.

The AX3500 controller moving one vehicle model and the NEO-6M reporting it, each on its own
pty, in a process apart from the platform's as real devices are (``bench_patrol`` measures the
platform's own CPU this way). The MPU-6050 is on I2C, which a pty cannot carry: it stays
emulated inside the platform's process (``platformd.sim.mpu6050``).
"""

from __future__ import annotations

import sys

from brasidas.bus import Bus
from brasidas.config import PlatformConfig
from platformd.sim.ax3500 import Ax3500Simulator, options_for
from platformd.sim.gps import GpsSimulator
from platformd.sim.vehicle import vehicle_for


async def serve(config: PlatformConfig) -> None:
    """The AX3500's pty path on stdout's first line (open it 8N1), the GPS's on the second
    (at ``gps.sim_rate_hz``); serves until cancelled."""
    vehicle = vehicle_for(config)
    controller = Ax3500Simulator(options_for(config.motor), vehicle=vehicle)
    controller.start()
    gps = GpsSimulator(Bus(), vehicle, config.gps.sim_rate_hz)
    try:
        sys.stdout.write(f"{controller.path}\n{gps.path}\n")
        sys.stdout.flush()
        await gps.run()
    finally:
        gps.close()
        controller.close()
