"""The station daemon's (and CLI's) configuration schema."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from brasidas.config.admission import STATION_RENAMED, AdmissionSection, station_admission
from brasidas.config.loader import (
    Check,
    Rule,
    above,
    at_least,
    bind_port,
    each,
    empty_or,
    fraction,
    host_name,
    ip_address,
    multicast_address,
    ordered,
    setting,
)
from brasidas.config.platform import SecuritySection

station_id = Check(
    "1-64 printable characters", lambda value: 0 < len(value) <= 64 and value.isprintable()
)
"""What a platform's ``connect`` accepts."""


@dataclass(frozen=True)
class StationSection:
    id: str = setting("station-1", station_id)
    api_host: str = setting("127.0.0.1", ip_address)
    """The station daemon's local API (CLI and browser console). Loopback only by default;
    which connections it holds, and how long, is ``[admission]``."""
    api_port: int = setting(8780, bind_port)
    connect_timeout: float = setting(3.0, above(0, most=300))
    """How long a command waits for the platform's acknowledgement."""


@dataclass(frozen=True)
class DiscoverySection:
    port: int = setting(21000, bind_port)
    bind_host: str = setting("0.0.0.0", ip_address)
    """Receive-only. 0.0.0.0 is needed to hear broadcasts; nothing is sent from here."""
    expiry: float = setting(4.0, above(0, most=3600))
    """A platform is dropped this long after its last beacon (R-9.3)."""
    groups: tuple[str, ...] = setting((), each(multicast_address))
    """Multicast groups to hear beacons on (R-0.6.1), e.g. ["239.255.21.0"]."""
    interfaces: tuple[str, ...] = setting((), each(ip_address))
    """Local addresses of the interfaces to join ``groups`` on. Empty: every interface."""


@dataclass(frozen=True)
class TeleopSection:
    rate_hz: float = setting(20.0, at_least(1, most=100))
    """$PVEL sentences per second to a platform while this station holds its manual override."""
    drive_timeout: float = setting(0.5, above(0, most=60))
    """A drive client (keyboard, console) silent for this long gets zeros streamed instead."""


@dataclass(frozen=True)
class JoystickSection:
    RULES: ClassVar[tuple[Rule, ...]] = (
        Rule(
            "angular_axis",
            "another axis than linear_axis",
            lambda s: s.angular_axis != s.linear_axis,
            ("linear_axis",),
        ),
    )

    device: str = ""
    """Linux joystick device, e.g. /dev/input/js0. Empty: no game controller."""
    platform: str = ""
    """Platform the controller drives. Empty: the one whose override this station took last."""
    enable_button: int = setting(4, at_least(0, most=255))
    """Button that must be held for the sticks to move the robot (LB on an F310 / Xbox pad)."""
    linear_axis: int = setting(1, at_least(0, most=255))
    """Axis for linear x (1: left stick vertical)."""
    angular_axis: int = setting(0, at_least(0, most=255))
    """Axis for angular z (0: left stick horizontal; 3: right stick horizontal)."""
    invert_linear: bool = True
    """Linux reports stick-up as negative; forward must be positive."""
    invert_angular: bool = True
    """Linux reports stick-left as negative; positive angular z turns left."""
    deadzone: float = setting(0.1, at_least(0, most=0.9))
    """Stick deflections below this fraction of full scale read as zero."""
    linear_scale: float = setting(1.0, fraction)
    """Full stick gives this linear command (0-1): a gentler robot for training."""
    angular_scale: float = setting(1.0, fraction)
    """Full stick gives this angular command (0-1)."""


@dataclass(frozen=True)
class TelemetryReceiverSection:
    RULES: ClassVar[tuple[Rule, ...]] = (
        ordered("battery_low_v", "battery_clear_v", strict=False),
        Rule(
            "controller_clear_c",
            "<= {section}.controller_max_c ({controller_max_c})",
            lambda s: s.controller_clear_c <= s.controller_max_c,
            ("controller_max_c",),
        ),
    )

    bind_host: str = setting("", empty_or(ip_address))
    """Where telemetry is received. Empty: 127.0.0.1 for a platform on loopback, else 0.0.0.0."""
    rate_hz: float = setting(0.0, at_least(0, most=50))
    """Datagrams per second asked of platforms. 0: the platform's configured rate."""
    battery_low_v: float = setting(23.0, above(0, most=100))
    """Low battery warning below this pack voltage (also raised when the platform says LOW)."""
    battery_clear_v: float = setting(23.4, above(0, most=100))
    """The low battery warning clears at or above this voltage."""
    controller_max_c: float = setting(70.0, at_least(-40, most=150))
    """Controller over-temperature warning at or above this heatsink temperature."""
    controller_clear_c: float = setting(65.0, at_least(-40, most=150))
    """The over-temperature warning clears below this temperature."""
    loss_warn_pct: float = setting(10.0, above(0, most=100))
    """Link degraded when more than this share of recent datagrams was lost."""
    loss_window: int = setting(50, at_least(1, most=10000))
    """How many recent sequence numbers the loss figure covers (10 s at 5 Hz)."""
    silence_s: float = setting(1.0, above(0, most=600))
    """Link degraded when no valid datagram arrived for this long."""
    refused_warn: int = setting(100, at_least(1, most=1_000_000))
    """Warning 90.24 when the platform refused at least this many connections from one address
    within its tally window (10 s): a host without the fleet key hammering signaling."""


@dataclass(frozen=True)
class StationMediaSection:
    microphone_device: str = ""
    """ALSA capture device for talking to a platform. Empty: the default."""
    speaker_device: str = ""
    """ALSA playback device for a platform's microphone. Empty: the default."""


@dataclass(frozen=True)
class ConsoleSection:
    RULES: ClassVar[tuple[Rule, ...]] = (
        Rule(
            "tls_key",
            "set exactly when {section}.tls_cert is",
            lambda s: bool(s.tls_cert) == bool(s.tls_key),
            ("tls_cert",),
        ),
    )

    drive_timeout: float = setting(0.2, above(0, most=5))
    """A console page's drive input lasts this long unless repeated (it sends at 20 Hz): a
    page that goes quiet stops the robot within this plus one $PVEL period."""
    tls_cert: str = ""
    """PEM certificate (chain) for serving the console and local API over HTTPS as well, for an
    operator on another host (the browser's video decoder needs a secure context: plain HTTP
    qualifies only on 127.0.0.1/localhost). Empty: no HTTPS."""
    tls_key: str = ""
    """PEM private key of ``tls_cert``."""
    https_host: str = setting("0.0.0.0", ip_address)
    """Where the HTTPS console listens (with ``tls_cert``)."""
    https_port: int = setting(8743, bind_port)
    https_names: tuple[str, ...] = setting((), each(host_name))
    """Host names (or addresses) operators open the HTTPS console by, e.g. ["station.local"]:
    any other Host header is refused (DNS rebinding), as on the loopback API."""
    tls_client_ca: str = ""
    """PEM CA bundle: when set, HTTPS clients must present a certificate it signed (the local
    API has no login of its own, and it can move the robot)."""
    tiles: str = ""
    """The map's offline background (issue 31): an MBTiles file (a path ending .mbtiles) or a
    tile URL template ("http://tiles.lan/{z}/{x}/{y}.png"), served to the console at
    /tiles/{z}/{x}/{y}; a URL's tiles are kept in ``tiles_cache`` and served from there
    offline. Empty: no tiles (the grid, the area image)."""
    tiles_cache: str = ""
    """Where a tile URL's tiles are kept. Empty: $XDG_STATE_HOME/brasidas/tiles."""


@dataclass(frozen=True)
class FoxgloveSection:
    """Live Foxglove WebSocket server (issue 23): every connected platform's channels."""

    enabled: bool = True
    host: str = setting("127.0.0.1", ip_address)
    """Where it listens: loopback unless an operator elsewhere needs it."""
    port: int = setting(8766, bind_port)
    """0: any free port (tests)."""
    video: bool = True
    """Serve the NavCam (H.264 access units as foxglove.CompressedVideo)."""
    origins: tuple[str, ...] = ()
    """Web origins whose pages may connect besides the server's own (the console's rule: any
    other ``Origin`` is answered 403), e.g. ``["https://app.foxglove.dev"]`` for Foxglove's
    web app. Clients that send no ``Origin`` (Foxglove desktop, scripts) are not affected."""
    platform_prefix: bool = False
    """Every platform's topics carry its id (``/rover-1/navcam``). False: the first platform
    connected has a recording's names (``/navcam``), so one Foxglove layout works live and on
    files; each other platform connected meanwhile is told apart by its id."""


@dataclass(frozen=True)
class ReplaySection:
    """The console's replay cache (issue 23): recordings fetched from platforms to replay,
    in ``$XDG_STATE_HOME/brasidas/replay``."""

    max_bytes: int = setting(4 * 1024**3, at_least(1024 * 1024, most=2**50))
    """The cache's total size; past it the least recently opened recordings are deleted."""


@dataclass(frozen=True)
class StationConfig:
    RENAMED: ClassVar[dict[str, str]] = STATION_RENAMED

    station: StationSection = field(default_factory=StationSection)
    admission: AdmissionSection = field(default_factory=station_admission)
    security: SecuritySection = field(default_factory=SecuritySection)
    discovery: DiscoverySection = field(default_factory=DiscoverySection)
    telemetry: TelemetryReceiverSection = field(default_factory=TelemetryReceiverSection)
    teleop: TeleopSection = field(default_factory=TeleopSection)
    joystick: JoystickSection = field(default_factory=JoystickSection)
    media: StationMediaSection = field(default_factory=StationMediaSection)
    console: ConsoleSection = field(default_factory=ConsoleSection)
    foxglove: FoxgloveSection = field(default_factory=FoxgloveSection)
    replay: ReplaySection = field(default_factory=ReplaySection)
