"""Simulated hardware for ``--sim``: the real drivers talk to these through ptys and an I2C map.

The simulators start before every subsystem (:func:`platformd.app.start_simulators`); the
context then names what the drivers open (``ctx.motor_serial``, ``ctx.gps_port``,
``ctx.positional_lights_output``, ``ctx.sim.i2c_bus``), so no configuration is rewritten.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the simulators import the context, which holds this
    from brasidas.drivers.mpu6050 import BusFactory
    from platformd.sim.ax3500 import Ax3500Simulator
    from platformd.sim.carmen import CarmenSimulator
    from platformd.sim.gpio import SimulatedGpio
    from platformd.sim.gps import GpsSimulator
    from platformd.sim.lidar import LidarSimulator
    from platformd.sim.mpu6050 import Mpu6050
    from platformd.sim.turret import TurretSimulator
    from platformd.sim.vehicle import VehicleModel


@dataclass(frozen=True)
class SimulatedDevices:
    """The simulated devices of one platform; all None without ``--sim``."""

    vehicle: VehicleModel | None = None
    """The one vehicle model the simulators share (motor commands move it, sensors read it)."""
    ax3500: Ax3500Simulator | None = None
    """The motor controller, on a pty (its 8N1 line is ``ctx.motor_serial``)."""
    gpio: SimulatedGpio | None = None
    """GPIO chips standing in for the machine's (libgpiod's request API), when the positional
    lights are not configured: they then hang on :data:`platformd.sim.gpio.SIM_LIGHTS_OUTPUT`."""
    gps: GpsSimulator | None = None
    """The NEO-6M, on a pty; None when ``gps.port`` names another device."""
    mpu6050: Mpu6050 | None = None
    i2c_bus: BusFactory | None = None
    """Opens the emulated I2C bus with the MPU-6050 on it, instead of ``smbus2.SMBus``."""
    turret: TurretSimulator | None = None
    """The turret's microcontroller, on a pty (``payload.enabled`` names the turret)."""
    lidar: LidarSimulator | None = None
    """The 2-D lidar on the vehicle, on a pty (``lidar.enabled``)."""
    lidar_replay: CarmenSimulator | None = None
    """The lidar replaying ``sim.carmen_file`` instead (then ``lidar`` is None)."""
