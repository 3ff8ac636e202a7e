"""The platform daemon: builds the context, sets up each subsystem, serves until stopped."""

from __future__ import annotations

import importlib
import logging
import time

from brasidas.actor import Daemon
from brasidas.codecs.jsonrpc import Dispatcher
from brasidas.config import PlatformConfig
from brasidas.sdnotify import Notifier, WatchdogPinger
from platformd.context import PlatformContext

_LOGGER = logging.getLogger(__name__)

SUBSYSTEMS: tuple[str, ...] = (
    # Order matters: simulators first (they create the ptys the drivers open), then the
    # drivers, then what reports on them. Each module has ``async def async_setup(ctx)``.
    "platformd.sim.gps",
    "platformd.sim.mpu6050",
    "platformd.sim.ax3500",  # --sim only: sets motor.port to its pty
    "platformd.sessions",
    "platformd.mode",
    "platformd.velocity",
    "platformd.arbiter",
    "platformd.motor",  # obeys the arbiter's MOTOR_COMMAND
    "platformd.gps",
    "platformd.imu",
    "platformd.media",
    "platformd.telemetry",
    "platformd.signaling",
    "platformd.beacon",  # after signaling: the beacon carries its bound URL
)


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
        for name in SUBSYSTEMS:
            module = importlib.import_module(name)
            await module.async_setup(self.ctx)
        _LOGGER.info(
            "platform %s up: signaling %s", self.config.platform.id, self.ctx.signaling_url
        )
        if self.notifier.enabled:  # under systemd (Type=notify)
            self.supervisor.start(WatchdogPinger(self.bus, self.notifier))
            self.notifier.ready(f"serving {self.ctx.signaling_url}")
