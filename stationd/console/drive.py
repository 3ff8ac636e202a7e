"""The console's override and drive feed: the page that engaged the override drives, for
``console.drive_timeout`` after each input only (a page that stops sending stops the robot)."""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from brasidas.codecs.jsonrpc import CallContext, RpcError
from stationd.console.session import ConsoleParts, ConsoleSession
from stationd.teleop import STOP

NOT_DRIVING = -32011
_LOGGER = logging.getLogger(__name__)


class ConsoleDrive(ConsoleParts):
    """Override and drive for the pages."""

    # ------------------------------------------------------------------ override and drive

    async def api_console_override(
        self, call: CallContext, platform_id: str, engaged: bool, force: bool = False
    ) -> dict[str, Any]:
        """Engage or release the manual override; the page that engaged it is the one driving.
        ``force`` takes control from another station (``movrd --force``)."""
        session = self._session(call)
        answer: dict[str, Any] = await self.ctx.api.call_local(
            "movrd", platform_id=platform_id, engaged=engaged, force=force
        )
        if answer.get("accepted"):
            if engaged:
                self.drivers[platform_id] = session.number
            else:
                self._stop_driving(session, platform_id)
                self.drivers.pop(platform_id, None)
        self._mark_dirty()
        return answer

    async def api_console_drive(
        self, call: CallContext, platform_id: str, linear: float, angular: float
    ) -> dict[str, Any]:
        """This page's velocity for the next ``console.drive_timeout`` seconds."""
        session = self._session(call)
        if self.drivers.get(platform_id) != session.number:
            raise RpcError(NOT_DRIVING, f"this console does not hold {platform_id}'s override")
        answer: dict[str, Any] = await self.ctx.api.call_local(
            "teleop_set", platform_id=platform_id, linear=linear, angular=angular
        )
        if session.closed:  # the page went away meanwhile
            self._stop_driving(session, platform_id)
            return answer
        stop = session.drive_stops.pop(platform_id, None)
        if stop is not None:
            stop.cancel()
        session.drive_stops[platform_id] = asyncio.get_running_loop().call_later(
            self.ctx.config.console.drive_timeout, self._stop_driving, session, platform_id
        )
        return answer

    def _stop_driving(self, session: ConsoleSession, platform_id: str) -> None:
        """Zero the drive input at once (the sender streams zeros from its next tick)."""
        stop = session.drive_stops.pop(platform_id, None)
        if stop is not None:
            stop.cancel()
        if self.ctx.teleop is not None:
            self.ctx.teleop.set_drive(platform_id, STOP)

    def _release_when_gone(self, session: ConsoleSession, platform_id: str) -> None:
        """The driving page closed: release its override after the drive deadman, as a cut
        link would be, unless another page engaged it meanwhile (issue 27: an engaged
        override left behind kept a patrol suspended indefinitely)."""
        if self._group is None:
            return
        self._group.create_task(
            self._release_after(session.number, platform_id),
            name=f"console:{session.number}:release:{platform_id}",
        )

    async def _release_after(self, number: int, platform_id: str) -> None:
        await asyncio.sleep(self.ctx.config.console.drive_timeout)
        if self.drivers.get(platform_id) != number:
            return  # another page engaged it since
        self.drivers.pop(platform_id, None)
        try:
            answer = await self.ctx.api.call_local("movrd", platform_id=platform_id, engaged=False)
        except RpcError as err:
            _LOGGER.warning("%s: the closed page's override not released: %s", platform_id, err)
            return
        _LOGGER.warning("%s: the driving page closed: override released (%s)", platform_id, answer)
        self._mark_dirty()
