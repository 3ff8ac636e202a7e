"""The failsafe ladder (issue 13, item 4): what a teleoperated robot does when its link goes.

While the manual override is engaged, the holder's link is watched: any call (stations send a
heartbeat every ``signaling.heartbeat_interval``) or authentic velocity datagram refreshes it:

1. no valid velocity for ``velocity.deadman`` (300 ms): motors at zero — the motion arbiter's
   deadman, resumed by the next valid packet;
2. silent for ``failsafe.hold_after`` (1.5 s): **hold** — motors at zero, payloads safe, and
   every velocity dropped (counted as ``held``) until the operator re-engages the override: a
   link that comes back never resumes an old command, nor a burst of delayed ones;
3. silent for ``failsafe.release_after`` (10 s): with ``failsafe.action = release`` the override
   is released and autonomy resumes (R-17); with ``hold`` the robot keeps holding.

Each step is logged, published on ``FAILSAFE_STATE`` (telemetry's ``failsafe`` section; the
station raises a group 90 LINK LOST notification from it).
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import Callable

from brasidas import topics
from brasidas.actor import Actor
from brasidas.codecs.telemetry_schema import Failsafe
from brasidas.messages import FailsafeState, FailsafeStep, OverrideState
from platformd.context import PlatformContext

_LOGGER = logging.getLogger(__name__)

TICK = 0.02
"""Seconds between checks: the ladder's steps land within this of their time."""


class FailsafeLadder(Actor):
    """Watches the override holder's session; steps to hold and release. ``tick(now)`` is the
    whole decision (tests drive it with their own clock)."""

    name = "failsafe"

    def __init__(self, ctx: PlatformContext, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self.config = ctx.config.failsafe
        self._clock = clock
        self.state = FailsafeState()
        self.steps: dict[str, int] = {"hold": 0, "released": 0}

    async def run(self) -> None:
        self.subscribe(topics.OVERRIDE_STATE, self._on_override)
        self.bus.publish(topics.FAILSAFE_STATE, self.state)
        while True:
            await asyncio.sleep(TICK)
            self.tick(self._clock())

    def tick(self, now: float) -> None:
        """Step the ladder for the holder's silence at ``now`` (session clock)."""
        override = self.bus.last(topics.OVERRIDE_STATE)
        if override is None or not override.engaged:
            return
        session = self.ctx.session(override.session_id)
        if session is None:
            return  # its session ended: the mode arbiter releases the override
        silent = now - max(session.last_seen, session.last_velocity)
        step = self.state.step
        if step is FailsafeStep.NORMAL and silent >= self.config.hold_after:
            self._step(
                FailsafeStep.HOLD,
                session.station_id,
                f"no heartbeat from {session.station_id} for {silent:.2f} s: holding",
            )
        elif (
            step is FailsafeStep.HOLD
            and self.config.action == "release"
            and silent >= self.config.release_after
        ):
            self._step(
                FailsafeStep.RELEASED,
                session.station_id,
                f"no heartbeat from {session.station_id} for {silent:.2f} s: override released",
            )

    def _on_override(self, state: OverrideState) -> None:
        # Engaging (again) is the operator's deliberate act: the ladder starts over. The mode
        # arbiter publishes an engage request during a hold even though nothing changes.
        if state.engaged and self.state.step is not FailsafeStep.NORMAL:
            self._step(FailsafeStep.NORMAL, state.station_id, "re-engaged by the operator")
        elif not state.engaged and self.state.step is FailsafeStep.HOLD:
            self._step(FailsafeStep.NORMAL, None, "override released")

    def _step(self, step: FailsafeStep, station_id: str | None, reason: str) -> None:
        if step is not FailsafeStep.NORMAL:
            self.steps[step.value] += 1
            _LOGGER.warning("failsafe: %s", reason)
        else:
            _LOGGER.info("failsafe: normal (%s)", reason)
        self.state = FailsafeState(step, station_id, reason)
        self.bus.publish(topics.FAILSAFE_STATE, self.state)

    def section(self) -> Failsafe:
        """The ``failsafe`` telemetry section."""
        return Failsafe(self.state.step.value, self.state.reason, self.ctx.authority.station_id)


async def async_setup(ctx: PlatformContext) -> None:
    ladder = FailsafeLadder(ctx)
    ctx.telemetry.register(Failsafe, ladder.section)
    ctx.telemetry.add_counters("failsafe", lambda: dict(ladder.steps))
    ctx.supervisor.start(ladder)
