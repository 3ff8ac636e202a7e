"""The station's local API for arming and stopping (issue 27): ``arm``, ``disarm``, ``stop``.

``stop`` and ``disarm`` are for every operator (an observer's session too): stopping never
needs control. ``arm`` needs control: the platform's refusal comes back with its reason
(``control held by station alpha``, or every failing pre-arm check).
"""

from __future__ import annotations

from typing import Any

from brasidas.codecs.jsonrpc import CallContext
from stationd.context import StationContext

METHODS = ("arm", "disarm", "stop")


class ArmingApi:
    def __init__(self, ctx: StationContext) -> None:
        self.ctx = ctx

    async def _call(self, platform_id: str, method: str, **params: Any) -> Any:
        connection = await self.ctx.connection(platform_id)
        return await connection.call(method, **params)

    async def api_arm(self, call: CallContext, platform_id: str) -> Any:
        """Arm through the platform's pre-arm checks (needs control)."""
        return await self._call(platform_id, "arm")

    async def api_disarm(self, call: CallContext, platform_id: str, force: bool = False) -> Any:
        """Disarm: motors held at zero, the patrol stopped (anyone)."""
        return await self._call(platform_id, "disarm", force=bool(force))

    async def api_stop(self, call: CallContext, platform_id: str) -> Any:
        """The emergency stop/hold: disarmed, the patrol stopped, who recorded (anyone)."""
        return await self._call(platform_id, "stop")


async def async_setup(ctx: StationContext) -> None:
    api = ArmingApi(ctx)
    for name in METHODS:
        ctx.api.add(name, getattr(api, f"api_{name}"), session_required=False)
