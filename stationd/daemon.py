"""The station daemon: discovery, platform sessions, and the local API for the CLI and console."""

from __future__ import annotations

import logging
import ssl
from pathlib import Path
from types import ModuleType

from aiohttp import web

from brasidas import subsystems
from brasidas.actor import Daemon
from brasidas.admission import ServerAdmission, admission_limits
from brasidas.codecs.jsonrpc import Dispatcher
from brasidas.codecs.telemetry_schema import schema_document
from brasidas.config import ConfigError, ConsoleSection, StationConfig
from brasidas.limits import STATION_API_MAX_BYTES
from brasidas.rpc import ADMISSION, add_rpc_routes, serve_app_sites
from stationd.context import StationContext
from stationd.tiles import add_tile_routes

_LOGGER = logging.getLogger(__name__)

SUBSYSTEMS: tuple[str, ...] = (
    # Each module has ``async def async_setup(ctx: StationContext)``.
    "stationd.discovery",
    "stationd.connections",
    "stationd.telemetry",
    "stationd.teleop",
    "stationd.media",
    "stationd.patrol",
    "stationd.arming",
    "stationd.mapfiles",
    "stationd.perception",
    "stationd.recordings",
    "stationd.console",
    "stationd.foxglove_live",  # after the console: it shares its video feeds
)

WEB_ROOT = Path(__file__).parent / "web"
"""The browser console, installed with the package (in a source tree, a link to ``web/``)."""
UPLOT_ROOT = Path(__file__).resolve().parent.parent / "node_modules" / "uplot" / "dist"
"""uPlot from npm (``make deps``: package-lock.json), served at /static/uplot, never copied."""
LEAFLET_ROOT = Path("/usr/share/javascript/leaflet")
"""Debian's libjs-leaflet (``make deps``), served at /static/leaflet, never copied."""
CONTENT_SECURITY_POLICY = (
    "default-src 'self'; script-src 'self'; worker-src 'self'; connect-src 'self'; "
    "img-src 'self' data: blob:; style-src 'self'; object-src 'none'; base-uri 'none'; "
    "frame-ancestors 'none'; form-action 'none'"
)
"""The console's pages: scripts from the station only (no inline script, no eval)."""
API_MAX_BYTES = STATION_API_MAX_BYTES
"""A map or route file's text as a JSON string and the call around it (brasidas.limits)."""


def load_subsystems(config: StationConfig) -> tuple[ModuleType, ...]:
    """Every subsystem's module in order, and what the enabled ones will import, imported now:
    before the loop runs, or before the daemon's first actor (brasidas.subsystems)."""
    return subsystems.load(SUBSYSTEMS, config)


class ConsoleMissing(Exception):
    """The browser console's files are not installed."""


class StationDaemon(Daemon):
    """One station: discovery, sessions, the local API and the console; ``start``/``stop``."""

    def __init__(self, config: StationConfig, fleet_key: bytes | None) -> None:
        self.config = config
        super().__init__()
        self.ctx = StationContext(
            config=config,
            bus=self.bus,
            supervisor=self.supervisor,
            api=Dispatcher(max_batch=config.admission.max_batch),
            fleet_key=fleet_key,
        )
        self.app = web.Application(client_max_size=API_MAX_BYTES)
        self.api_port = 0
        """The local API's bound port (``station.api_port``, or the kernel's choice for 0)."""
        self.api_url = ""
        self.console_https_port: int | None = None
        """The HTTPS console's bound port (with ``console.tls_cert``)."""
        self.api_admission: ServerAdmission | None = None
        """The local API's connections and their admission counters, once bound."""

    async def start(self) -> None:
        if not (
            WEB_ROOT / "index.html"
        ).is_file():  # a broken install, found before anything starts
            raise ConsoleMissing(f"no browser console: {WEB_ROOT / 'index.html'} is missing")
        console = self.config.console
        tls_sites = []
        if console.tls_cert:  # a bad certificate stops the daemon before anything starts
            tls_sites.append((console.https_host, console.https_port, tls_context(console)))
        setups = load_subsystems(self.config)  # before the first actor: imports block the loop
        for module in setups:
            await module.async_setup(self.ctx)
        local_hosts = frozenset(
            {"127.0.0.1", "localhost", "[::1]", self.config.station.api_host, *console.https_names}
        )
        # Uncompressed: the console's socket carries the NavCam (see add_rpc_routes).
        add_rpc_routes(
            self.app,
            self.ctx.api,
            "/api/rpc",
            API_MAX_BYTES,
            local_hosts=local_hosts,
            compress=False,
        )
        self.app.router.add_get("/api/telemetry-schema.json", _telemetry_schema)
        _add_console_routes(self.app)
        add_tile_routes(self.app, console)
        station = self.config.station
        port, *tls_ports = await serve_app_sites(
            self.app,
            station.api_host,
            station.api_port,
            supervisor=self.supervisor,
            bus=self.bus,
            name="api",
            tls_sites=tls_sites,
            limits=admission_limits(self.config.admission),
        )
        self.api_port = port
        self.api_admission = self.app[ADMISSION]
        self.api_url = f"http://{station.api_host}:{port}"
        _LOGGER.info("station %s up: local API %s", station.id, self.api_url)
        if tls_ports:
            self.console_https_port = tls_ports[0]
            names = ", ".join(console.https_names) or "no host names (console.https_names)"
            _LOGGER.info("console over HTTPS on port %d for %s", tls_ports[0], names)


def tls_context(console: ConsoleSection) -> ssl.SSLContext:
    """The HTTPS console's server context; ConfigError names the key that cannot be loaded."""
    if not console.tls_key:
        raise ConfigError("console.tls_key", "required with console.tls_cert")
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    try:
        context.load_cert_chain(console.tls_cert, console.tls_key)
    except (OSError, ssl.SSLError) as err:
        raise ConfigError("console.tls_cert", f"cannot load with console.tls_key: {err}") from None
    if console.tls_client_ca:
        try:
            context.load_verify_locations(console.tls_client_ca)
        except (OSError, ssl.SSLError) as err:
            raise ConfigError("console.tls_client_ca", f"cannot load: {err}") from None
        context.verify_mode = ssl.CERT_REQUIRED
    return context


def _add_console_routes(app: web.Application) -> None:
    app.router.add_get("/", _index)
    if LEAFLET_ROOT.is_dir():
        app.router.add_static("/static/leaflet", LEAFLET_ROOT)
    else:
        _LOGGER.warning("no map in the console: %s missing (make deps)", LEAFLET_ROOT)
    if UPLOT_ROOT.is_dir():
        app.router.add_static("/static/uplot", UPLOT_ROOT)
    else:
        _LOGGER.warning("no plots in the console: %s missing (make deps)", UPLOT_ROOT)
    app.router.add_static("/static", WEB_ROOT)
    app.on_response_prepare.append(_security_headers)


async def _index(request: web.Request) -> web.FileResponse:
    return web.FileResponse(WEB_ROOT / "index.html")


async def _security_headers(request: web.Request, response: web.StreamResponse) -> None:
    response.headers.setdefault("Content-Security-Policy", CONTENT_SECURITY_POLICY)
    response.headers.setdefault("X-Content-Type-Options", "nosniff")
    response.headers.setdefault("Referrer-Policy", "no-referrer")


async def _telemetry_schema(request: web.Request) -> web.Response:
    """The telemetry schema the console reads snapshots by (brasidas.codecs.telemetry_schema)."""
    return web.json_response(schema_document())
