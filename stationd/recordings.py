"""The station's local API for a platform's recordings (issue 23): list them, and where to
download one (the platform's signaling URL and this station's session token: the CLI then
fetches the file itself, over HTTP with ranges, so a cut download resumes)."""

from __future__ import annotations

from typing import Any
from urllib.parse import quote

from brasidas.codecs.jsonrpc import CallContext
from stationd.context import StationContext

SESSION_HEADER = "X-Brasidas-Session"
"""The header the platform reads the session token from (platformd.recorder)."""


class RecordingsApi:
    def __init__(self, ctx: StationContext) -> None:
        self.ctx = ctx

    async def api_recordings_list(self, call: CallContext, platform_id: str) -> Any:
        """The platform's recordings and its recorder's state."""
        connection = await self.ctx.connection(platform_id)
        return await connection.call("list_recordings")

    async def api_recording_source(
        self, call: CallContext, platform_id: str, name: str
    ) -> dict[str, Any]:
        """Where to download recording ``name``: its URL and the header to send."""
        connection = await self.ctx.connection(platform_id)
        return {
            "url": f"{connection.signaling_url}/recordings/{quote(name, safe='')}",
            "headers": {SESSION_HEADER: connection.session_id},
        }


async def async_setup(ctx: StationContext) -> None:
    api = RecordingsApi(ctx)
    for name in ("recordings_list", "recording_source"):
        ctx.api.add(name, getattr(api, f"api_{name}"), session_required=False)
