"""What every platform subsystem gets at setup: config, bus, supervisor, RPC table, command
router, sessions, capabilities."""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Protocol

from aiohttp import web

from brasidas import topics
from brasidas.actor import Supervisor
from brasidas.admission import ServerAdmission, SourceLedger
from brasidas.bus import Bus
from brasidas.codecs.jsonrpc import Dispatcher
from brasidas.config import PlatformConfig
from brasidas.messages import CommandReceived, CommandResult, SessionClosed, SessionOpened
from brasidas.telemetry_sources import TelemetrySources
from platformd.authority import Authority
from platformd.commands import CommandRouter, SystemCommand
from platformd.session_table import Session, SessionTable
from platformd.sim import SimulatedDevices

if TYPE_CHECKING:
    from brasidas.autonomy.areamap import AreaMap
    from brasidas.autonomy.patrol import Patrol
    from brasidas.autonomy.route import Route
    from brasidas.media.video import AccessUnitSink
    from brasidas.messages import PatrolState


@dataclass(frozen=True)
class SerialDevice:
    """A serial line to open: the device and its framing."""

    path: str
    baudrate: int
    bytesize: int = 8
    parity: str = "N"
    stopbits: int = 1


class CapabilitySections:
    """The sections of ``connect``'s capabilities that subsystems add (``gps``, ``motor``,
    ``streams``, ...), each computed when a station connects. Write-only for subsystems: one
    owner per section (a second registration of a name is refused, as the command router
    refuses a second owner of a code), and nothing finds a service through it."""

    def __init__(self) -> None:
        self._providers: dict[str, Callable[[], Any]] = {}

    def register(self, name: str, provider: Callable[[], Any]) -> Callable[[], None]:
        """Add section ``name``; returns the function that removes it."""
        if name in self._providers:
            raise ValueError(f"capability section {name!r} is already registered")
        self._providers[name] = provider

        def remove() -> None:
            if self._providers.get(name) is provider:
                del self._providers[name]

        return remove

    def describe(self) -> dict[str, Any]:
        """Every section, computed now (JSON values)."""
        return {name: provider() for name, provider in self._providers.items()}


@dataclass(frozen=True)
class PayloadInfo:
    """A payload the platform carries, as it registered itself (platformd.payloads)."""

    name: str
    groups: tuple[int, ...]
    """Its command groups (100-110); each command's spec is the router's."""
    streams: tuple[str, ...] = ()
    """The media streams that are its own, e.g. the turret's thermal camera."""


class MediaHandle(Protocol):
    """What other subsystems use of the media service (platformd.media.MediaService)."""

    @property
    def navcam(self) -> object | None:
        """The NavCam stream, None on a platform without one."""

    def describe_streams(self) -> list[dict[str, Any]]:
        """Every stream's name, kind and state (the connect answer's ``streams``)."""

    def nav_camera(self) -> dict[str, Any]:
        """The NavCam's parameters (``get_nav_camera_parameters``)."""

    async def start_stream(
        self, name: str, host: str = "", port: int = 0, *, session_id: str | None = None
    ) -> object:
        """Start ``session_id``'s copy of a stream, sent to ``host:port``."""

    def bytes_sent(self, name: str, host: str, port: int) -> int:
        """Bytes stream ``name`` has sent to ``host:port`` since that destination was added
        (0 when it is not one)."""

    def tap_navcam(self, sink: AccessUnitSink) -> Callable[[], None] | None:
        """Give ``sink`` the NavCam's encoded access units; returns how to remove it, or None
        on a platform without a NavCam."""

    async def record_navcam(self, fps: int) -> object:
        """Keep the NavCam running for the recorder at ``fps`` while no station watches."""


class ArmingHandle(Protocol):
    """What other subsystems use of arming (platformd.arming.ArmingActor)."""

    armed: bool

    def arm(self, by: str, *, manual: bool = False) -> str | None:
        """Arm through the pre-arm checks: None, or the failing reasons."""

    async def stop(self, session: Session | None, word: str, *, force: bool = False) -> None:
        """Stop, hold or disarm on anyone's behalf; the last word kept on disk."""

    def reasons(self, *, manual: bool = False) -> tuple[str, ...]:
        """The failing pre-arm checks (empty: arming would pass)."""


class PatrolHandle(Protocol):
    """What other subsystems use of the patrol (platformd.autonomy.patrol.PatrolActor)."""

    @property
    def core(self) -> Patrol:
        """The patrol's own state, for tests to look into: subsystems read the accessors
        below and change it through the methods (tests/test_ports.py checks)."""

    @property
    def state(self) -> PatrolState:
        """Idle, patrolling, holding, stopped, ..."""

    @property
    def route(self) -> Route:
        """The route driven now (a go-to's while driving to one point)."""

    @property
    def area(self) -> AreaMap | None:
        """The map (boundary and keep-outs), None before one is loaded."""

    @property
    def map_revision(self) -> int:
        """Counts the map's changes: a fence made for one revision is not another's."""

    async def set_waypoints(
        self, items: list[Any], laps: int | None = None, home: tuple[float, float] | None = None
    ) -> Route:
        """Replace the route (``set_waypoints``'s checks); raises RouteError."""

    async def reshape_map(self, source: Mapping[str, Any]) -> AreaMap:
        """Replace boundary and keep-outs, keeping the route; raises MapError or RouteError."""

    resumable: bool
    """A stored route on an enabled patrol: what autostart resumes."""
    map_error: str
    start_check: Callable[[], str | None] | None
    """Before a start: a refusal (platformd.arming's pre-arm) or None."""
    on_stop: Callable[[], None] | None
    """After an operator's stop (platformd.arming)."""
    settle: Callable[[], Awaitable[None]] | None
    """Awaits the last word's write (platformd.arming)."""

    @property
    def detour(self) -> str | None:
        """Driving to one point (a go-to or RTL): its label; None otherwise."""

    async def go_to_point(self, latitude: float, longitude: float, label: str) -> Route:
        """Drive to one point through the planner and stop there; raises RouteError."""

    def start_patrol(self) -> None:
        """Start patrolling the route; raises RouteError."""

    def stop_patrol(self, *, operator: bool = True) -> None:
        """Stop now; ``operator`` False: a failsafe's stop, not kept as the last word."""

    async def update_map(
        self, add: Sequence[Mapping[str, Any]], remove: list[str], *, store: bool = True
    ) -> AreaMap:
        """Add or remove keep-outs (``store=False``: not written to ``map.file``); raises
        MapError."""

    def go_to_waypoint(self, index: int) -> None:
        """Head for waypoint ``index`` (from 0) next; raises RouteError."""


@dataclass
class PlatformContext:
    config: PlatformConfig
    bus: Bus
    supervisor: Supervisor
    rpc: Dispatcher
    """Signaling methods: ``rpc.add(name, handler)``; handlers take ``(ctx: CallContext, **params)``."""
    fleet_key: bytes | None
    """None only with --insecure."""
    signaling_url: str = ""
    """Where stations reach signaling; set once the server is bound (before the beacon starts)."""
    velocity_port: int = 0
    """The UDP port velocity datagrams arrive on; set once bound (the kernel's choice for 0)."""
    signaling_admission: ServerAdmission | None = None
    """Signaling's connections and their admission counters; set once the server is bound."""
    sim: SimulatedDevices = field(default_factory=SimulatedDevices)
    """The simulated devices (``--sim``), started before every subsystem."""
    sessions: SessionTable = field(default_factory=SessionTable)
    """The open sessions, kept by the session manager (platformd.sessions)."""
    commands: CommandRouter = field(init=False)
    """System commands: ``commands.register(owner, {code: handler})`` (platformd.commands)."""
    authority: Authority = field(init=False)
    """Who holds control (platformd.authority); the router asks it before every command."""
    capabilities: CapabilitySections = field(default_factory=CapabilitySections)
    """Sections of the ``connect`` answer's capabilities: ``capabilities.register(name, f)``."""
    telemetry: TelemetrySources = field(default_factory=TelemetrySources)
    """Sources of the telemetry snapshot's sections, by schema type, and diagnostics counters."""
    media: MediaHandle | None = None
    """The media service (streams, NavCam), set by its setup (platformd.media)."""
    payloads: dict[str, PayloadInfo] = field(default_factory=dict)
    """The payloads carried, by name (platformd.payloads): none without ``payload.enabled``."""
    boot: int = 0
    """This start's boot number (platformd.boot_counter; only grows), set by the beacon's setup;
    0 without beacons."""
    mavlink_port: int = 0
    """The MAVLink endpoint's bound UDP port (platformd.mavlink), 0 when it is off."""
    patrol: PatrolHandle | None = None
    arming: ArmingHandle | None = None
    """Armed or not, the stop for everyone (platformd.arming)."""
    """The patrol (platformd.autonomy): its route and map, for the MAVLink endpoint."""
    egress: SourceLedger = field(default_factory=SourceLedger)
    """Bytes sent on each source address's behalf, every path through it: MAVLink answers,
    the video a MAVLink request started, recording downloads (brasidas.admission)."""
    http_routes: list[web.RouteDef] = field(default_factory=list)
    """Plain HTTP routes served beside signaling's (the recorder's downloads); added before
    signaling's setup."""

    @property
    def motor_serial(self) -> SerialDevice:
        """The motor controller's line: ``motor.*``, or in --sim the simulator's pty (8N1: a pty
        refuses 7 bits and parity, hardware.md; the bytes are the same ASCII)."""
        if self.sim.ax3500 is not None:
            return SerialDevice(self.sim.ax3500.path, self.config.motor.baudrate)
        motor = self.config.motor
        return SerialDevice(
            motor.port, motor.baudrate, motor.bytesize, motor.parity, motor.stopbits
        )

    @property
    def positional_lights_output(self) -> str:
        """``motor.positional_lights_output``; when empty in --sim, a line of the simulated
        GPIO chip (``ctx.sim.gpio``)."""
        configured = self.config.motor.positional_lights_output
        if not configured and self.sim.gpio is not None:
            from platformd.sim.gpio import SIM_LIGHTS_OUTPUT

            return SIM_LIGHTS_OUTPUT
        return configured

    @property
    def gps_port(self) -> str:
        """The NMEA receiver's device: ``gps.port``, or in --sim the simulator's pty."""
        return self.sim.gps.path if self.sim.gps is not None else self.config.gps.port

    def __post_init__(self) -> None:
        self.commands = CommandRouter(self.config.signaling.command_timeout)
        self.authority = Authority(self.bus, self.sessions, self.commands.is_engagement)
        self.commands.authorize = self.authority.authorize
        self.authority.command_name = self.commands.spec_name
        self.commands.on_answered = self._command_answered
        self.sessions.announce = self._announce_session

    def _announce_session(self, event: SessionOpened | SessionClosed) -> None:
        if isinstance(event, SessionOpened):
            self.bus.publish(topics.SESSION_OPENED, event)
        else:
            self.bus.publish(topics.SESSION_CLOSED, event)

    def _command_answered(self, command: SystemCommand, result: CommandResult) -> None:
        session = command.session
        self.bus.publish(
            topics.COMMAND_RECEIVED,
            CommandReceived(
                "system",
                str(command.code),
                command.payload,
                session.session_id if session else None,
                session.station_id if session else None,
                result.accepted,
                result.reason,
            ),
        )

    def session(self, session_id: str | None) -> Session | None:
        """The open session with this token, or None."""
        return self.sessions.get(session_id)

    @property
    def session_count(self) -> int:
        return len(self.sessions)
