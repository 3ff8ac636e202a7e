"""The motor controller driver: a Roboteq AX3500 on a serial line (the seed's "vmci").

Layers: :mod:`brasidas.codecs.ax3500` (sans-IO) → :mod:`.link` (one open serial
connection with one command in flight; pyserial-asyncio's callbacks only feed the codec) →
:mod:`.controller` (the actor that reopens the link with capped backoff, brings the controller
up and decides what to send next); :mod:`.lights` holds the lights and their outputs.

What it sends, in priority order:

1. the velocity, when ``MOTOR_COMMAND`` (the motion arbiter) changed it. **Latest wins**: the
   newest command replaces any not yet sent, so the line never holds a backlog;
2. accessory outputs (lights, 10.6/10.7);
3. a refresh (channel 1 again) when nothing was sent for ``1 / refresh_hz`` (the controller's
   watchdog stops the motors after 1 s of silence; a ``W`` or ``OK`` resends both channels). A command that repeats the current one
   and arrives after most of that period triggers the refresh at once, so in teleop the
   refreshes go out right behind a stream packet rather than at a random moment;
4. status polls (``?e ?m ?a``), only right behind a velocity exchange: in teleop the line is
   then free again before the next packet arrives.

A ``-`` answer is resent once, then reported. ``max_unanswered`` silent commands in a row, an
I/O error or a vanished port close the link; the actor reports it on ``CONTROLLER_STATUS``,
retries with backoff and, when the controller is back, starts from zero: a velocity that
arrived before or during the outage is never replayed. On shutdown (it stops first) it
commands zero before the line closes.
"""

from __future__ import annotations

from typing import Any

from brasidas.clock import Clock
from brasidas.codecs.telemetry_schema import Motor
from brasidas.config import PlatformConfig
from brasidas.config.platform import GPIO_PREFIX
from platformd.context import PlatformContext
from platformd.motor.controller import MotorController
from platformd.motor.link import LinkError, ReplyTimeout, SerialLink

__all__ = ["LinkError", "MotorController", "ReplyTimeout", "SerialLink", "async_setup", "preload"]


def preload(config: PlatformConfig) -> None:
    """libgpiod's driver when a light hangs off a GPIO line (in --sim, the positional lights
    when no output is configured: platformd.context)."""
    motor = config.motor
    outputs = (motor.main_lights_output, motor.positional_lights_output)
    on_gpio = any(output.strip().startswith(GPIO_PREFIX) for output in outputs)
    if motor.enabled and (on_gpio or (config.sim.enabled and not motor.positional_lights_output)):
        import platformd.motor.gpio  # noqa: F401


def capability(controller: MotorController) -> dict[str, Any]:
    """The ``motor`` section of the connect answer."""
    return {
        "controller": "Roboteq AX3500",
        "port": controller.device.path,
        "lights": controller.lights.fitted(),
        "refresh_hz": round(1.0 / controller.refresh_period, 1),
    }


async def async_setup(ctx: PlatformContext, *, clock: Clock | None = None) -> None:
    """Start the driver (``clock``: a test's, else the event loop's)."""
    if not ctx.config.motor.enabled:
        return
    controller = MotorController(ctx, clock=clock)
    ctx.capabilities.register("motor", lambda: capability(controller))
    ctx.telemetry.register(Motor, controller.snapshot)
    ctx.telemetry.add_counters("motor", lambda: controller.counters)
    ctx.supervisor.start(controller)
