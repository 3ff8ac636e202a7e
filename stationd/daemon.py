"""The station daemon: discovery, platform sessions, and the local API for the CLI and console."""

from __future__ import annotations

import importlib
import logging
from pathlib import Path

from aiohttp import web

from brasidas.actor import Daemon
from brasidas.codecs.jsonrpc import Dispatcher
from brasidas.config import StationConfig
from brasidas.rpc import add_rpc_routes, serve_app
from stationd.context import StationContext

_LOGGER = logging.getLogger(__name__)

SUBSYSTEMS: tuple[str, ...] = (
    # Each module has ``async def async_setup(ctx: StationContext)``.
    "stationd.discovery",
    "stationd.connections",
    "stationd.telemetry",
    "stationd.teleop",
    "stationd.media",
    "stationd.console",
)

WEB_ROOT = Path(__file__).resolve().parent.parent / "web"
LEAFLET_ROOT = Path("/usr/share/javascript/leaflet")
"""Debian's libjs-leaflet (``make deps``), served at /static/leaflet, never copied."""
CONTENT_SECURITY_POLICY = (
    "default-src 'self'; script-src 'self'; worker-src 'self'; connect-src 'self'; "
    "img-src 'self' data: blob:; style-src 'self'; object-src 'none'; base-uri 'none'; "
    "frame-ancestors 'none'; form-action 'none'"
)
"""The console's pages: scripts from the station only (no inline script, no eval)."""
API_MAX_BYTES = 65536


class StationDaemon(Daemon):
    """One station: discovery, sessions, the local API and the console; ``start``/``stop``."""

    def __init__(self, config: StationConfig, fleet_key: bytes | None) -> None:
        self.config = config
        super().__init__()
        self.ctx = StationContext(
            config=config,
            bus=self.bus,
            supervisor=self.supervisor,
            api=Dispatcher(),
            fleet_key=fleet_key,
        )
        self.app = web.Application(client_max_size=API_MAX_BYTES)
        self.api_url = ""

    async def start(self) -> None:
        for name in SUBSYSTEMS:
            await importlib.import_module(name).async_setup(self.ctx)
        local_hosts = frozenset({"127.0.0.1", "localhost", "[::1]", self.config.station.api_host})
        add_rpc_routes(self.app, self.ctx.api, "/api/rpc", API_MAX_BYTES, local_hosts=local_hosts)
        if (WEB_ROOT / "index.html").exists():
            _add_console_routes(self.app)
        station = self.config.station
        port = await serve_app(
            self.app,
            station.api_host,
            station.api_port,
            supervisor=self.supervisor,
            bus=self.bus,
            name="api",
        )
        station.api_port = port
        self.api_url = f"http://{station.api_host}:{port}"
        _LOGGER.info("station %s up: local API %s", station.id, self.api_url)


def _add_console_routes(app: web.Application) -> None:
    app.router.add_get("/", _index)
    if LEAFLET_ROOT.is_dir():
        app.router.add_static("/static/leaflet", LEAFLET_ROOT)
    else:
        _LOGGER.warning("no map in the console: %s missing (make deps)", LEAFLET_ROOT)
    app.router.add_static("/static", WEB_ROOT)
    app.on_response_prepare.append(_security_headers)


async def _index(request: web.Request) -> web.FileResponse:
    return web.FileResponse(WEB_ROOT / "index.html")


async def _security_headers(request: web.Request, response: web.StreamResponse) -> None:
    response.headers.setdefault("Content-Security-Policy", CONTENT_SECURITY_POLICY)
    response.headers.setdefault("X-Content-Type-Options", "nosniff")
    response.headers.setdefault("Referrer-Policy", "no-referrer")
