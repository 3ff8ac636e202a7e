"""The actor that closes a simulated device when the daemon stops."""

from __future__ import annotations

from typing import Protocol

from brasidas.actor import Actor, wait_forever
from brasidas.bus import Bus


class Closeable(Protocol):
    def close(self) -> None: ...


class SimulatorOwner(Actor):
    """Closes a simulated device (its pty) when the daemon stops, after its driver's last
    words (the motor's zero): it stops last."""

    restart = False
    stop_priority = -100

    def __init__(self, bus: Bus, name: str, simulator: Closeable) -> None:
        super().__init__(bus)
        self.name = name
        self.simulator = simulator

    async def run(self) -> None:
        try:
            await wait_forever()
        finally:
            self.simulator.close()
