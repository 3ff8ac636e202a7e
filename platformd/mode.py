"""Mode arbiter: the manual override (MOVRD, command 10.0) and who holds it (R-5, R-17).

Autonomous Mode is the default. One session at a time may hold the override; it is released
when that session disengages, disconnects or times out.
"""

from __future__ import annotations

import logging

from brasidas import topics
from brasidas.actor import Actor, wait_forever
from brasidas.codecs.commands import MANUAL_OVERRIDE, PayloadError, parse_switch
from brasidas.messages import (
    CommandResult,
    ControlState,
    FailsafeState,
    FailsafeStep,
    OverrideState,
    SessionClosed,
)
from platformd.commands import SystemCommand
from platformd.context import PlatformContext
from platformd.session_table import Session

_LOGGER = logging.getLogger(__name__)


class ModeArbiter(Actor):
    name = "mode"

    def __init__(self, ctx: PlatformContext) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self.state = OverrideState(engaged=False)

    async def run(self) -> None:
        self.on_remove(self.ctx.commands.register(self.name, {MANUAL_OVERRIDE: self._command}))
        self.subscribe(topics.SESSION_CLOSED, self._on_session_closed)
        self.subscribe(topics.CONTROL_STATE, self._on_control)
        self.subscribe(topics.FAILSAFE_STATE, self._on_failsafe)
        self.bus.publish(topics.OVERRIDE_STATE, self.state)
        await wait_forever()

    async def _command(self, command: SystemCommand) -> CommandResult:
        try:
            engage = parse_switch(command.payload)
        except PayloadError as err:
            return CommandResult(False, str(err))
        return self.request(engage, command.session)

    def request(self, engage: bool, session: Session | None) -> CommandResult:
        """Engage or disengage on behalf of ``session``; the answer says whether it took."""
        held_by = self.state.session_id
        session_id = session.session_id if session is not None else None
        if engage:
            if self.state.engaged and held_by != session_id:
                return CommandResult(False, f"manual override held by {self.state.station_id}")
            if session is None:
                return CommandResult(False, "manual override needs a station session")
            engaged = OverrideState(True, session.session_id, session.station_id)
            failsafe = self.bus.last(topics.FAILSAFE_STATE)
            if engaged == self.state and failsafe and failsafe.step is not FailsafeStep.NORMAL:
                # Re-engaging after a failsafe hold: the operator's deliberate act ends it.
                self.bus.publish(topics.OVERRIDE_STATE, engaged)
            self._set(engaged)
            return CommandResult(True, result={"engaged": True})
        if self.state.engaged and held_by != session_id:
            return CommandResult(False, f"manual override held by {self.state.station_id}")
        self._set(OverrideState(False))
        return CommandResult(True, result={"engaged": False})

    def _on_session_closed(self, event: SessionClosed) -> None:
        if self.state.engaged and self.state.session_id == event.session_id:
            _LOGGER.warning(
                "manual override released: session of %s ended (%s)", event.station_id, event.reason
            )
            self._set(OverrideState(False))

    def _on_control(self, control: ControlState) -> None:
        # Control taken by another station: its override goes first, before the taker's request.
        if self.state.engaged and self.state.session_id != control.session_id:
            _LOGGER.warning(
                "manual override of %s released: %s", self.state.station_id, control.reason
            )
            self._set(OverrideState(False))

    def _on_failsafe(self, failsafe: FailsafeState) -> None:
        if failsafe.step is FailsafeStep.RELEASED and self.state.engaged:
            _LOGGER.warning("manual override released by the failsafe: %s", failsafe.reason)
            self._set(OverrideState(False))

    def _set(self, state: OverrideState) -> None:
        if state == self.state:
            return
        self.state = state
        _LOGGER.info("mode: %s", state.mode.value)
        self.bus.publish(topics.OVERRIDE_STATE, state)


async def async_setup(ctx: PlatformContext) -> None:
    ctx.supervisor.start(ModeArbiter(ctx))
