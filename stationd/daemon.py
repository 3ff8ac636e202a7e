"""The station daemon: discovery, platform sessions, and the local API for the CLI and console."""

from __future__ import annotations

import asyncio
import contextlib
import importlib
import logging
from pathlib import Path

from aiohttp import web

from brasidas.actor import Actor, Supervisor, wait_forever
from brasidas.bus import Bus
from brasidas.codecs.jsonrpc import Dispatcher
from brasidas.config import StationConfig
from brasidas.rpc import add_rpc_routes
from stationd.context import StationContext

_LOGGER = logging.getLogger(__name__)

SUBSYSTEMS: tuple[str, ...] = (
    # Each module has ``async def async_setup(ctx: StationContext)``.
    "stationd.discovery",
    "stationd.connections",
    "stationd.telemetry",
    "stationd.teleop",
    "stationd.media",
)

WEB_ROOT = Path(__file__).resolve().parent.parent / "web"
API_MAX_BYTES = 65536


class ApiServer(Actor):
    """Owns the local API's aiohttp runner (bound during start, cleaned up on stop)."""

    name = "api"
    restart = False

    def __init__(self, bus: Bus, runner: web.AppRunner) -> None:
        super().__init__(bus)
        self.runner = runner

    async def run(self) -> None:
        try:
            await wait_forever()
        finally:
            with contextlib.suppress(Exception):
                await asyncio.shield(self.runner.cleanup())


class StationDaemon:
    def __init__(self, config: StationConfig, fleet_key: bytes | None) -> None:
        self.config = config
        self.bus = Bus()
        self.supervisor = Supervisor()
        self.ctx = StationContext(
            config=config,
            bus=self.bus,
            supervisor=self.supervisor,
            api=Dispatcher(),
            fleet_key=fleet_key,
        )
        self.app = web.Application(client_max_size=API_MAX_BYTES)
        self.api_url = ""
        self._stopped = False

    async def start(self) -> None:
        for name in SUBSYSTEMS:
            await importlib.import_module(name).async_setup(self.ctx)
        local_hosts = frozenset({"127.0.0.1", "localhost", "[::1]", self.config.station.api_host})
        add_rpc_routes(self.app, self.ctx.api, "/api/rpc", API_MAX_BYTES, local_hosts=local_hosts)
        if (WEB_ROOT / "index.html").exists():
            self.app.router.add_get("/", _index)
            self.app.router.add_static("/static", WEB_ROOT)
        runner = web.AppRunner(
            self.app, access_log=None, handle_signals=False, shutdown_timeout=0.2
        )
        await runner.setup()
        station = self.config.station
        site = web.TCPSite(runner, station.api_host, station.api_port, reuse_address=True)
        try:
            await site.start()
        except OSError:
            await runner.cleanup()
            raise
        port = runner.addresses[0][1] if runner.addresses else station.api_port
        station.api_port = port
        self.api_url = f"http://{station.api_host}:{port}"
        self.supervisor.start(ApiServer(self.bus, runner))
        _LOGGER.info("station %s up: local API %s", station.id, self.api_url)

    async def stop(self, timeout: float = 0.9) -> None:
        if self._stopped:
            return
        self._stopped = True
        await self.supervisor.stop(timeout)

    async def run(self, stop: asyncio.Event) -> None:
        try:
            await self.start()
            await stop.wait()
        finally:
            await self.stop()


async def _index(request: web.Request) -> web.FileResponse:
    return web.FileResponse(WEB_ROOT / "index.html")
