"""The station's local API for a platform's lidar view (issue 30): ``perception_grid``, the
platform's occupancy grid as a small image (the console draws it under the scan; its
revision is in the ``lidar_view`` telemetry section). Checked before it is passed on: a
platform's answer that is not a grid image is refused with the reason.
"""

from __future__ import annotations

from typing import Any

from brasidas.codecs.jsonrpc import INTERNAL_ERROR, CallContext, RpcError
from brasidas.perception.view import GridRefused, grid_from_json
from stationd.context import StationContext

METHODS = ("perception_grid",)


class PerceptionApi:
    def __init__(self, ctx: StationContext) -> None:
        self.ctx = ctx

    async def api_perception_grid(self, call: CallContext, platform_id: str) -> Any:
        """The platform's occupancy grid image (``{"rev": 0}`` while it has none)."""
        connection = await self.ctx.connection(platform_id)
        answer = await connection.call("get_grid")
        if isinstance(answer, dict) and answer.get("rev") == 0:
            return answer
        try:
            grid_from_json(answer if isinstance(answer, dict) else {})
        except GridRefused as err:
            raise RpcError(INTERNAL_ERROR, f"grid from {platform_id} refused: {err}") from None
        return answer


async def async_setup(ctx: StationContext) -> None:
    api = PerceptionApi(ctx)
    for name in METHODS:
        ctx.api.add(name, getattr(api, f"api_{name}"), session_required=False)
