"""The platform daemon: builds the context, sets up each subsystem, serves until stopped."""

from __future__ import annotations

import logging
import time
from types import ModuleType
from typing import TYPE_CHECKING

from brasidas import subsystems
from brasidas.actor import Daemon
from brasidas.codecs.jsonrpc import Dispatcher
from brasidas.config import PlatformConfig
from brasidas.sdnotify import Notifier, WatchdogPinger
from platformd.context import PlatformContext
from platformd.sim import SimulatedDevices
from platformd.sim import ax3500 as ax3500_sim
from platformd.sim import gps as gps_sim
from platformd.sim import mpu6050 as mpu6050_sim
from platformd.sim import turret as turret_sim
from platformd.sim.vehicle import vehicle_for

if TYPE_CHECKING:  # Shapely loads with the first map, not at start
    from brasidas.autonomy.areamap import AreaMap

_LOGGER = logging.getLogger(__name__)

SUBSYSTEMS: tuple[str, ...] = (
    # Each module has ``async def async_setup(ctx)``. Most meet only on the bus (retained
    # values) and could come in any order; three orderings remain, each for a reason:
    # telemetry's own sections are defaults that never replace a driver's, so it comes after
    # the drivers; signaling serves the RPC table as soon as it is bound, so it comes after
    # every module that adds methods or capabilities; the beacon advertises signaling's bound
    # URL (its setup refuses to run before). The simulators are not subsystems: they are
    # started before all of these (start_simulators), so the drivers open them.
    "platformd.sessions",
    "platformd.mode",
    "platformd.velocity",
    "platformd.arbiter",
    "platformd.failsafe",
    "platformd.speedcap",
    "platformd.motor",
    "platformd.gps",
    "platformd.imu",
    "platformd.lidar",  # before autonomy: the arbiter's limits from the first scan
    "platformd.autonomy",  # localization (POSE) and the patrol (CMD_VEL)
    "platformd.arming",  # after autonomy (it hooks ctx.patrol), before mavlink (ctx.arming)
    "platformd.media",
    "platformd.payloads",
    "platformd.mavlink",  # after autonomy and media: ctx.patrol, ctx.media
    "platformd.telemetry",
    "platformd.recorder",  # after media (it taps the NavCam), before signaling (its routes)
    "platformd.signaling",
    "platformd.beacon",
)


def load_subsystems(config: PlatformConfig) -> tuple[ModuleType, ...]:
    """Every subsystem's module in order, and what the simulators and the enabled subsystems
    will import, imported now: before the loop runs, or before the daemon's first actor
    (brasidas.subsystems)."""
    modules = subsystems.load(SUBSYSTEMS, config)
    if config.sim.enabled:
        if config.motor.enabled and not config.motor.positional_lights_output:
            import platformd.sim.gpio
        if config.lidar.enabled and config.sim.carmen_file:
            import platformd.sim.carmen
        elif config.lidar.enabled:
            import platformd.sim.lidar  # noqa: F401
    return modules


async def start_simulators(ctx: PlatformContext) -> SimulatedDevices:
    """In ``--sim``: the simulated vehicle and the devices the enabled drivers will open."""
    config = ctx.config
    if not config.sim.enabled:
        return SimulatedDevices()
    vehicle = vehicle_for(config)
    ax3500 = gpio = gps = chip = i2c_bus = None
    if config.motor.enabled:
        ax3500 = ax3500_sim.start_simulator(ctx.bus, ctx.supervisor, config.motor, vehicle)
        if not config.motor.positional_lights_output:
            # The AX3500 has one accessory output (C); the positional lights hang off a GPIO
            # line, as on the Pi: a simulated chip stands in for libgpiod's.
            from platformd.sim.gpio import SimulatedGpio

            gpio = SimulatedGpio()
    if config.gps.enabled:
        receiver = gps_sim.RECEIVERS[config.sim.gps_receiver]
        gps = gps_sim.start_simulator(ctx.bus, ctx.supervisor, config.gps, vehicle, receiver)
    if config.imu.enabled:
        chip, i2c_bus = mpu6050_sim.emulate(config.imu, vehicle)
    turret = None
    if "turret" in config.payload.enabled:
        turret = turret_sim.start_simulator(ctx.bus, ctx.supervisor, config.payload)
    lidar = lidar_replay = None
    if config.lidar.enabled and config.sim.carmen_file:
        from platformd.sim.carmen import CarmenSimulator

        lidar_replay = CarmenSimulator(ctx.bus, config.sim.carmen_file, config.lidar)
        ctx.supervisor.start(lidar_replay)
    elif config.lidar.enabled:
        from platformd.sim import lidar as lidar_sim

        def area() -> AreaMap | None:  # the patrol's map, once autonomy has set up
            return ctx.patrol.area if ctx.patrol is not None else None

        lidar = lidar_sim.start_simulator(ctx.bus, ctx.supervisor, config, vehicle, area)
    return SimulatedDevices(vehicle, ax3500, gpio, gps, chip, i2c_bus, turret, lidar, lidar_replay)


class PlatformDaemon(Daemon):
    """One platform: ``await start()``, then ``await stop()`` (idempotent, bounded)."""

    def __init__(
        self, config: PlatformConfig, fleet_key: bytes | None, notifier: Notifier | None = None
    ) -> None:
        self.config = config
        self.notifier = notifier or Notifier()
        super().__init__()
        self.ctx = PlatformContext(
            config=config,
            bus=self.bus,
            supervisor=self.supervisor,
            rpc=Dispatcher(),
            fleet_key=fleet_key,
        )
        self.started_at = time.monotonic()

    async def start(self) -> None:
        setups = load_subsystems(self.config)  # before the first actor: imports block the loop
        self.ctx.sim = await start_simulators(self.ctx)
        for module in setups:
            await module.async_setup(self.ctx)
        _LOGGER.info(
            "platform %s up: signaling %s", self.config.platform.id, self.ctx.signaling_url
        )
        if self.notifier.enabled:  # under systemd (Type=notify)
            self.supervisor.start(WatchdogPinger(self.bus, self.notifier))
            self.notifier.ready(f"serving {self.ctx.signaling_url}")

    async def stop(self, timeout: float = 0.9) -> None:
        """Tell systemd STOPPING=1 (if SIGTERM did not already), then stop every actor."""
        self.notifier.stopping()
        await super().stop(timeout)
