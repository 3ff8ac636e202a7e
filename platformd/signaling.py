"""Signaling, the common protocol (R-10, R-14): JSON-RPC 2.0 over aiohttp at /rpc and /rpc/ws.

``issue_system_command``, ``set_manual_override`` and ``set_lights`` go through the command
router (``ctx.commands``, platformd.commands): the subsystem that registered the code answers;
codes nobody handles are rejected with the reason (known codes) or answered with an error
(unknown codes), never silence.
"""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from aiohttp import web

from brasidas.admission import COUNTERS, REFUSAL_WINDOW, ServerAdmission, admission_limits
from brasidas.codecs.commands import MAIN_LIGHTS, MANUAL_OVERRIDE, POSITIONAL_LIGHTS, CommandCode
from brasidas.codecs.jsonrpc import (
    CONTROL_REFUSED,
    INVALID_PARAMS,
    UNAVAILABLE,
    CallContext,
    RpcError,
)
from brasidas.codecs.telemetry_schema import SCHEMA_VERSION, Admission, snapshot_to_json
from brasidas.rpc import ADMISSION, add_rpc_routes, serve_app
from platformd.context import PlatformContext
from platformd.sessions import platform_parameters, velocity_endpoint

_LOGGER = logging.getLogger(__name__)


class Signaling:
    """The common protocol's methods."""

    def __init__(self, ctx: PlatformContext) -> None:
        self.ctx = ctx

    async def issue_system_command(
        self, call: CallContext, group: int, command: int, payload: str = ""
    ) -> dict[str, Any]:
        if not 0 <= group <= 255 or not 0 <= command <= 255:
            raise RpcError(INVALID_PARAMS, "invalid params: group and command must be 0-255")
        result = await self.ctx.commands.dispatch(
            CommandCode(group, command), payload, call.session
        )
        return result.as_dict()

    async def set_manual_override(self, call: CallContext, engaged: bool) -> bool:
        """True once done; a refusal is an error (CONTROL_REFUSED) naming who holds control,
        never a bare false."""
        result = await self.ctx.commands.dispatch(
            MANUAL_OVERRIDE, "True" if engaged else "False", call.session
        )
        if not result.accepted:
            raise RpcError(CONTROL_REFUSED, result.reason or "manual override refused")
        return True

    async def set_lights(self, call: CallContext, which: str, on: bool) -> dict[str, Any]:
        """Main (10.6) or positional (10.7) lights; the seed's set_lights/set_pos_lights."""
        codes = {"main": MAIN_LIGHTS, "positional": POSITIONAL_LIGHTS, "pos": POSITIONAL_LIGHTS}
        if which not in codes:
            raise RpcError(INVALID_PARAMS, "invalid params: which must be main or positional")
        result = await self.ctx.commands.dispatch(codes[which], "ON" if on else "OFF", call.session)
        return result.as_dict()

    def get_platform_parameters(self, call: CallContext) -> dict[str, Any]:
        return platform_parameters(self.ctx)

    def get_velocity_connection_info(self, call: CallContext) -> dict[str, Any]:
        return velocity_endpoint(self.ctx)

    def get_nav_camera_parameters(self, call: CallContext) -> dict[str, Any]:
        media = self.ctx.media
        if media is None or media.navcam is None:
            raise RpcError(UNAVAILABLE, "this platform has no NavCam")
        return media.nav_camera()

    def get_telemetry_report(self, call: CallContext) -> dict[str, Any]:
        """The snapshot the stream carries, by the schema's long names."""
        return {
            "platform_id": self.ctx.config.platform.id,
            "schema": SCHEMA_VERSION,
            **snapshot_to_json(self.ctx.telemetry.build()),
        }


ADMISSION_COUNTERS = tuple(name for name in COUNTERS if name != "accepted")
"""What telemetry's admission section carries of the admission counters (not ``accepted``)."""


def admission_section(admission: ServerAdmission, rpc_counters: dict[str, int]) -> Admission:
    """Telemetry's admission section. Runs on the event loop (its clock is the admission's)."""
    counters = admission.counters()
    carried = {name: counters.get(name, 0) for name in ADMISSION_COUNTERS}
    carried["refused_batches"] = rpc_counters.get("refused_batches", 0)
    host, refused = admission.top_refused(asyncio.get_running_loop().time())
    return Admission(
        counters={name: value for name, value in carried.items() if value},
        strangers=admission.stranger_count(),
        refusing=host,
        refused=refused,
        window_s=REFUSAL_WINDOW if refused else 0.0,
    )


async def async_setup(ctx: PlatformContext) -> None:
    signaling = Signaling(ctx)
    for name in (
        "issue_system_command",
        "set_manual_override",
        "set_lights",
        "get_platform_parameters",
        "get_velocity_connection_info",
        "get_nav_camera_parameters",
        "get_telemetry_report",
    ):
        ctx.rpc.add(name, getattr(signaling, name))
    config = ctx.config.signaling
    ctx.rpc.max_batch = ctx.config.admission.max_batch
    ctx.rpc.max_answer_bytes = config.max_answer_bytes
    app = web.Application(client_max_size=config.max_request_bytes)
    add_rpc_routes(app, ctx.rpc, "/rpc", config.max_request_bytes)
    app.router.add_routes(ctx.http_routes)
    port = await serve_app(
        app,
        config.host,
        config.port,
        supervisor=ctx.supervisor,
        bus=ctx.bus,
        name="signaling",
        limits=admission_limits(ctx.config.admission),
    )
    ctx.signaling_admission = admission = app[ADMISSION]
    ctx.telemetry.register(Admission, lambda: admission_section(admission, ctx.rpc.counters))
    # With port 0 the kernel chose one; beacons must carry the real one.
    ctx.signaling_url = f"http://{config.advertise_host or config.host}:{port}"
