"""Motion arbiter: which source drives the motors, by mode (R-5), with the teleop deadman.

Autonomous Mode (the default): ``CMD_VEL`` goes to ``MOTOR_COMMAND``. With the manual override
engaged: ``TELEOP_VELOCITY`` (the ``$PVEL`` stream) goes to ``MOTOR_COMMAND`` and ``CMD_VEL`` is
ignored. Every switch commands zero first, so a robot never carries one source's speed into the
other's mode. The switch happens inside the ``OVERRIDE_STATE`` delivery, which is synchronous,
so by the time the mode arbiter answers an engage request the motors already obey the stream.

Proximity (issue 30): in every mode, the linear speed is clamped to the lidar's limits for
what it sees ahead, along the arc the command turns, and behind (``PROXIMITY``,
platformd.lidar), down to zero with the reason.

Deadman: in teleop, when no valid velocity has arrived for ``velocity.deadman`` seconds, the
command becomes zero until the next valid packet.
"""

from __future__ import annotations

import asyncio
import logging
import math
from collections.abc import Callable
from typing import Protocol

from brasidas import topics
from brasidas.actor import Actor, wait_forever
from brasidas.bus import Bus
from brasidas.codecs.telemetry_schema import Motion
from brasidas.messages import (
    ArmingState,
    FailsafeState,
    FailsafeStep,
    Mode,
    MotionState,
    OverrideState,
    SpeedCap,
    Velocity,
)
from brasidas.perception.limits import limit_for
from brasidas.perception.messages import Proximity
from platformd.context import PlatformContext

_LOGGER = logging.getLogger(__name__)

STOP = Velocity(0.0, 0.0)
_TIMER_SLACK = 1e-4
"""Timers fire on float sums of the clock; never re-arm for a rounding error's worth."""


class TimerHandle(Protocol):
    def cancel(self) -> None: ...


Clock = Callable[[], float]
CallLater = Callable[[float, Callable[[], None]], TimerHandle]


class MotionArbiter(Actor):
    """Routes the mode's velocity source to ``MOTOR_COMMAND``; enforces the teleop deadman.

    ``clock`` and ``call_later`` default to the running loop's; tests pass a manual clock.
    """

    name = "arbiter"

    def __init__(
        self,
        bus: Bus,
        *,
        deadman: float,
        clock: Clock | None = None,
        call_later: CallLater | None = None,
    ) -> None:
        super().__init__(bus)
        self.deadman = deadman
        self._clock = clock
        self._call_later = call_later
        self.mode = Mode.AUTONOMOUS
        self.deadman_tripped = False
        self.deadman_trips = 0
        self.held = False
        self.cap = 1.0
        """The speed cap (platformd.speedcap): teleop linear speed clamped to ±this."""
        """The failsafe ladder holds: motors at zero, the stream ignored until re-engaged."""
        self.armed = True
        """Disarmed (platformd.arming): nothing but zero reaches the motors."""
        self.proximity: Proximity | None = None
        """The lidar's speed limits (None: no lidar, no limit)."""
        self.command = STOP
        self._last_valid = 0.0
        self._timer: TimerHandle | None = None
        self._reported: tuple[Mode, bool, Velocity] | None = None

    async def run(self) -> None:
        self.start()
        try:
            await wait_forever()
        finally:
            self._cancel_timer()

    def start(self) -> None:
        """Subscribe (and take the current override state). Must run on the event loop."""
        if self._clock is None or self._call_later is None:
            loop = asyncio.get_running_loop()
            self._clock = self._clock or loop.time
            self._call_later = self._call_later or loop.call_later
        self.subscribe(topics.CMD_VEL, self._on_cmd_vel)
        self.subscribe(topics.TELEOP_VELOCITY, self._on_teleop_velocity)
        self.subscribe(topics.OVERRIDE_STATE, self._on_override)
        self.subscribe(topics.FAILSAFE_STATE, self._on_failsafe)
        self.subscribe(topics.SPEED_CAP, self._on_speed_cap)
        self.subscribe(topics.ARMING_STATE, self._on_arming)
        self.subscribe(topics.PROXIMITY, self._on_proximity)
        self._publish(self.command)

    async def async_stop(self) -> None:
        self._cancel_timer()
        self._publish(STOP)

    def snapshot(self) -> MotionState:
        return MotionState(self.mode, self.deadman_tripped, self.command)

    def motion_section(self) -> Motion:
        """The ``motion`` telemetry section."""
        return Motion(
            self.mode.value, self.deadman_tripped, self.command.linear, self.command.angular
        )

    # ------------------------------------------------------------------ sources

    def _on_override(self, state: OverrideState) -> None:
        if state.mode is self.mode:
            return
        self.mode = state.mode
        _LOGGER.info("motors now follow %s", "the velocity stream" if state.engaged else "cmd_vel")
        self._cancel_timer()
        # Until the first valid packet, teleop holds the motors at zero: the deadman is "tripped".
        self.deadman_tripped = state.engaged
        self._publish(STOP)

    def _on_cmd_vel(self, velocity: Velocity) -> None:
        if self.mode is Mode.AUTONOMOUS:
            self._publish(velocity)

    def _on_failsafe(self, state: FailsafeState) -> None:
        held = state.step is FailsafeStep.HOLD
        if held == self.held:
            return
        self.held = held
        if held:
            self._cancel_timer()
            self.deadman_tripped = True
            self._publish(STOP)

    def _on_arming(self, state: ArmingState) -> None:
        if state.armed == self.armed:
            return
        self.armed = state.armed
        if not state.armed:
            self._cancel_timer()
            self.deadman_tripped = self.mode is Mode.TELEOP
            self._publish(STOP)

    def _on_speed_cap(self, cap: SpeedCap) -> None:
        self.cap = cap.fraction
        if self.mode is Mode.TELEOP and abs(self.command.linear) > self.cap:
            self._publish(self._capped(self.command))

    def _on_proximity(self, limits: Proximity) -> None:
        self.proximity = limits
        if self._near_limited(self.command) != self.command:
            self._publish(self.command)

    def _near_limited(self, velocity: Velocity) -> Velocity:
        limits = self.proximity
        if limits is None:
            return velocity
        forward, _why = limit_for(limits, velocity.linear, velocity.angular)
        if velocity.linear > forward:
            return Velocity(forward, velocity.angular)
        if -velocity.linear > limits.reverse_limit:
            return Velocity(-limits.reverse_limit, velocity.angular)
        return velocity

    def _capped(self, velocity: Velocity) -> Velocity:
        if abs(velocity.linear) <= self.cap:
            return velocity
        return Velocity(math.copysign(self.cap, velocity.linear), velocity.angular)

    def _on_teleop_velocity(self, velocity: Velocity) -> None:
        if self.mode is not Mode.TELEOP or self.held:
            return
        velocity = self._capped(velocity)
        assert self._clock is not None
        self._last_valid = self._clock()
        self.deadman_tripped = False
        if self._timer is None:
            self._arm(self.deadman)
        self._publish(velocity)

    # ------------------------------------------------------------------ deadman

    def _arm(self, delay: float) -> None:
        assert self._call_later is not None
        self._timer = self._call_later(delay, self._on_deadman_timer)

    def _on_deadman_timer(self) -> None:
        # One timer per deadman period rather than one per packet: at 500 Hz, re-arming on
        # every datagram would churn the loop's timer heap for nothing.
        self._timer = None
        if self.mode is not Mode.TELEOP:
            return
        assert self._clock is not None
        silent = self._clock() - self._last_valid
        if silent < self.deadman - _TIMER_SLACK:
            self._arm(self.deadman - silent)
            return
        self.deadman_tripped = True
        self.deadman_trips += 1
        _LOGGER.warning("deadman: no valid velocity for %.0f ms, motors to zero", silent * 1000)
        self._publish(STOP)

    def _cancel_timer(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _publish(self, velocity: Velocity) -> None:
        velocity = self._near_limited(velocity)
        if not self.armed:
            velocity = STOP
        self.command = velocity
        self.bus.publish(topics.MOTOR_COMMAND, velocity)
        state = (self.mode, self.deadman_tripped, velocity)
        if state != self._reported:
            self._reported = state
            self.bus.publish(topics.MOTION_STATE, self.snapshot())


async def async_setup(ctx: PlatformContext) -> None:
    arbiter = MotionArbiter(ctx.bus, deadman=ctx.config.velocity.deadman)
    ctx.telemetry.register(Motion, arbiter.motion_section)
    ctx.telemetry.add_counters("arbiter", lambda: {"deadman_trips": arbiter.deadman_trips})
    ctx.supervisor.start(arbiter)
