"""Configuration: TOML files over documented defaults, with command-line overrides.

Every section is a dataclass declared here, so all keys, types and defaults live in one
place and ``brasidas-platform config`` can print them. Loading rejects unknown keys and
wrong types with one line that names the file and the key (:class:`ConfigError`).
"""

from __future__ import annotations

import dataclasses
import itertools
import tomllib
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

C = TypeVar("C")


class ConfigError(Exception):
    """A configuration problem; the message names the file and the key."""


# --------------------------------------------------------------------------- platform


@dataclass
class PlatformSection:
    id: str = "brasidas-1"
    """Platform id: unique on the network, shown in discovery."""
    model: str = "Brasidas UGV"
    max_speed_kmh: float = 6.0
    """Top speed at full command (R-2.1), reported to stations."""


@dataclass
class SecuritySection:
    key_file: str = ""
    """Fleet key path. Empty: $XDG_STATE_HOME/brasidas/fleet.key."""
    insecure: bool = False
    """Run without a fleet key: no beacon HMAC, no authenticated connect. Never in the field."""


@dataclass
class SignalingSection:
    host: str = "127.0.0.1"
    port: int = 8765
    advertise_host: str = ""
    """Host put in the signaling URL of beacons. Empty: ``host``."""
    session_timeout: float = 5.0
    """A session with no heartbeat for this long ends (and releases the manual override)."""
    heartbeat_interval: float = 1.0
    """How often stations are told to send heartbeats."""
    max_request_bytes: int = 65536
    command_timeout: float = 3.0
    """How long a system command may take to be answered by its actor."""


@dataclass
class BeaconSection:
    enabled: bool = True
    port: int = 21000
    destinations: list[str] = field(default_factory=lambda: ["127.255.255.255"])
    """Where beacons go: broadcast, multicast group (R-0.6.1) or unicast addresses. The default
    is the loopback broadcast; deployments name the mesh's broadcast address or a group."""
    min_interval: float = 0.6
    max_interval: float = 3.0
    move_threshold_m: float = 1.0
    interface_host: str = "127.0.0.1"
    """Local address beacons are sent from (picks the interface, multicast ones included)."""
    multicast_ttl: int = 1
    """Hops a beacon to a multicast destination may cross: 1 stays on the segment; a routed
    mesh (OLSR, BATMAN at layer 3) needs its diameter."""
    listen: bool = True
    """Keep the list of the other platforms online from their beacons (R-9): list_platforms."""
    listen_host: str = "0.0.0.0"
    """Where this platform hears the others' beacons (on ``port``; it joins the multicast
    destinations on the interface of ``interface_host``)."""
    expiry: float = 4.0
    """Another platform is dropped from the list this long after its last beacon."""


@dataclass
class MotorSection:
    enabled: bool = True
    port: str = "/dev/ttyUSB0"
    """Serial device of the AX3500. In --sim, the simulator's pty replaces it."""
    baudrate: int = 9600
    bytesize: int = 7
    parity: str = "E"
    stopbits: int = 1
    linear_scale: float = 1.0
    """Fraction of full power (7F) that linear x = 1 commands on channel 1 (a gentler robot)."""
    angular_scale: float = 1.0
    """Fraction of full power that angular z = 1 commands on channel 2."""
    linear_limit: float = 1.0
    """Hard cap on channel 1 after scaling, as a fraction of full power."""
    angular_limit: float = 1.0
    """Hard cap on channel 2 after scaling, as a fraction of full power."""
    invert_linear: bool = False
    """Channel 1 forward drives this chassis backwards (wiring)."""
    invert_angular: bool = False
    """False: a left turn (positive angular z) is !B; true when !b turns left (wiring)."""
    refresh_hz: float = 10.0
    """Resend the commanded velocity this often even when unchanged (the watchdog needs >= 2)."""
    poll_hz: float = 1.0
    """Status polls (?e battery, ?m heatsinks, ?a amps) per second; 0: never."""
    reply_timeout: float = 0.3
    """Seconds to wait for a command's echo and answer."""
    max_unanswered: int = 3
    """Consecutive unanswered commands after which the controller counts as gone (reconnect)."""
    configure_mode: bool = False
    """When the controller is not in RS-232-with-watchdog, mixed open-loop mode, write those
    settings to its flash and reset it. False (the default: never rewrite a controller's stored
    setup unasked): a wrong motor mode refuses to drive, with the reason (the input mode warns)."""
    reconnect_max: float = 5.0
    """Longest wait between attempts to reopen a missing or silent controller (backoff cap)."""
    main_lights_output: str = "C"
    """Main lights (10.6): a controller output letter, or "gpio:PATH" (a GPIO value file)."""
    positional_lights_output: str = ""
    """Positional lights (10.7), as main_lights_output. Empty: not fitted, 10.7 is refused."""


@dataclass
class VelocitySection:
    host: str = "127.0.0.1"
    """Where the platform listens for $PVEL datagrams."""
    port: int = 21001
    advertise_host: str = ""
    """Host given to stations by get_velocity_connection_info. Empty: ``host``."""
    deadman: float = 0.3
    """In teleop, no valid velocity for this long commands zero."""
    stats_interval: float = 1.0
    """How often the receiver's counters are published for telemetry (when they changed)."""


@dataclass
class GpsSection:
    enabled: bool = True
    port: str = "/dev/ttyAMA0"
    """Serial device of the NMEA receiver (8N1). In --sim, the simulator's pty replaces it."""
    baudrate: int = 9600
    fix_timeout: float = 3.0
    """Seconds without a fix (receiver silent or port gone) before the fix is reported lost."""
    sim_rate_hz: float = 1.0
    """Epochs per second of the simulated receiver (1-10; the NEO-6M defaults to 1)."""


@dataclass
class ImuSection:
    enabled: bool = True
    i2c_bus: int = 1
    """I2C bus number (/dev/i2c-N); the Raspberry Pi header is bus 1."""
    address: int = 0x68
    """0x68 with AD0 low, 0x69 with AD0 high."""
    rate_hz: float = 100.0
    """Samples read (and fused) per second."""
    fifo: bool = True
    """Let the chip queue samples in its FIFO and drain it ~10 times a second (a tenth of the
    wake-ups); false reads one 14-byte burst per sample, waking at rate_hz."""
    accel_range_g: int = 2
    """Accelerometer full scale: 2, 4, 8 or 16 g (ACCEL_CONFIG AFS_SEL)."""
    gyro_range_dps: int = 250
    """Gyro full scale: 250, 500, 1000 or 2000 deg/s (GYRO_CONFIG FS_SEL)."""
    madgwick_beta: float = 0.05
    """Madgwick filter gain: higher trusts the accelerometer more (faster, noisier)."""
    calibrate_s: float = 1.0
    """Seconds of stillness at start used to measure the gyro's zero-rate offset (0: off)."""


@dataclass
class TelemetrySection:
    rate_hz: float = 5.0
    """Datagrams per second pushed to a station that asked (request_telemetry)."""
    battery_low_v: float = 23.0
    """Pack voltage below which the coarse battery level is LOW (24 V lead-acid pack)."""
    battery_high_v: float = 25.0
    """Pack voltage at or above which the coarse level is HIGH; MEDIUM in between."""
    battery_monitor: bool = True
    """Report the coarse battery level when the controller's status has no 20.4 monitor flag."""


@dataclass
class NavCamSection:
    enabled: bool = True
    device: str = "/dev/video0"
    width: int = 640
    height: int = 480
    framerate: int = 30
    idle_framerate: int = 5
    """Framerate while the manual override is disengaged (seed ch. 10 §3.2)."""
    bitrate_kbps: int = 1500
    """H.264 bitrate; 1500 keeps 640x480@30 moving content under the seed's 1.6 Mbit/s."""
    port: int = 5600
    """UDP port on the station that the NavCam RTP stream is sent to."""
    format: str = "raw"
    """What the camera delivers at width x height @ framerate: "raw" or "mjpeg"."""
    encoder: str = ""
    """Force an H.264 encoder (v4l2h264enc, omxh264enc, x264enc, openh264enc). Empty: first found."""
    sim_pattern: str = "ball"
    """--sim source: a videotestsrc pattern (ball moves; smpte with sim_motion for bandwidth)."""
    sim_motion: int = 0
    """--sim source: videotestsrc horizontal-speed (pixels per frame); 0 for a still pattern."""


@dataclass
class AudioSection:
    enabled: bool = True
    """Two-way audio: platform microphone to the station, station microphone to the speaker."""
    source_device: str = ""
    """ALSA capture device (e.g. hw:1,0). Empty: the default. In --sim: a test tone."""
    sink_device: str = ""
    """ALSA playback device. Empty: the default. In --sim: discarded (fakesink)."""
    bitrate: int = 24000
    """Opus bitrate (bit/s) of the platform microphone."""
    out_port: int = 5602
    """UDP port on the station that the platform microphone is sent to."""
    in_host: str = "127.0.0.1"
    """Where the platform listens for the station's audio (the mesh address in deployments)."""
    in_port: int = 5604
    """UDP port the platform listens on for the station's audio."""


@dataclass
class PayloadCameraSection:
    enabled: bool = False
    """The payload IP camera (the seed's thermal AXIS), forwarded without re-encoding."""
    url: str = ""
    """RTSP URL of the camera, e.g. rtsp://192.168.1.90/axis-media/media.amp."""
    port: int = 5606
    """UDP port on the station that the camera's RTP stream is forwarded to."""
    latency_ms: int = 50
    """rtspsrc jitter buffer (the camera's own network hop)."""


@dataclass
class SimSection:
    enabled: bool = False
    """Set by --sim: simulated controller, GPS, IMU and camera behind the real drivers."""
    latitude: float = 37.9415
    """Where the simulated vehicle starts (degrees, WGS-84)."""
    longitude: float = 23.6530
    altitude_m: float = 42.0
    heading_deg: float = 0.0
    """Compass heading at start (clockwise from north)."""


@dataclass
class PlatformConfig:
    platform: PlatformSection = field(default_factory=PlatformSection)
    security: SecuritySection = field(default_factory=SecuritySection)
    signaling: SignalingSection = field(default_factory=SignalingSection)
    beacon: BeaconSection = field(default_factory=BeaconSection)
    motor: MotorSection = field(default_factory=MotorSection)
    velocity: VelocitySection = field(default_factory=VelocitySection)
    gps: GpsSection = field(default_factory=GpsSection)
    imu: ImuSection = field(default_factory=ImuSection)
    telemetry: TelemetrySection = field(default_factory=TelemetrySection)
    navcam: NavCamSection = field(default_factory=NavCamSection)
    audio: AudioSection = field(default_factory=AudioSection)
    payload_camera: PayloadCameraSection = field(default_factory=PayloadCameraSection)
    sim: SimSection = field(default_factory=SimSection)


# --------------------------------------------------------------------------- station


@dataclass
class StationSection:
    id: str = "station-1"
    api_host: str = "127.0.0.1"
    """The station daemon's local API (CLI and browser console). Loopback only by default."""
    api_port: int = 8780
    connect_timeout: float = 3.0
    """How long a command waits for the platform's acknowledgement."""


@dataclass
class DiscoverySection:
    port: int = 21000
    bind_host: str = "0.0.0.0"
    """Receive-only. 0.0.0.0 is needed to hear broadcasts; nothing is sent from here."""
    expiry: float = 4.0
    """A platform is dropped this long after its last beacon (R-9.3)."""
    groups: list[str] = field(default_factory=list)
    """Multicast groups to hear beacons on (R-0.6.1), e.g. ["239.255.21.0"]."""
    interfaces: list[str] = field(default_factory=list)
    """Local addresses of the interfaces to join ``groups`` on. Empty: every interface."""


@dataclass
class TeleopSection:
    rate_hz: float = 20.0
    """$PVEL sentences per second to a platform while this station holds its manual override."""
    drive_timeout: float = 0.5
    """A drive client (keyboard, console) silent for this long gets zeros streamed instead."""


@dataclass
class JoystickSection:
    device: str = ""
    """Linux joystick device, e.g. /dev/input/js0. Empty: no game controller."""
    platform: str = ""
    """Platform the controller drives. Empty: the one whose override this station took last."""
    enable_button: int = 4
    """Button that must be held for the sticks to move the robot (LB on an F310 / Xbox pad)."""
    linear_axis: int = 1
    """Axis for linear x (1: left stick vertical)."""
    angular_axis: int = 0
    """Axis for angular z (0: left stick horizontal; 3: right stick horizontal)."""
    invert_linear: bool = True
    """Linux reports stick-up as negative; forward must be positive."""
    invert_angular: bool = True
    """Linux reports stick-left as negative; positive angular z turns left."""
    deadzone: float = 0.1
    """Stick deflections below this fraction of full scale read as zero."""
    linear_scale: float = 1.0
    """Full stick gives this linear command (0-1): a gentler robot for training."""
    angular_scale: float = 1.0
    """Full stick gives this angular command (0-1)."""


@dataclass
class TelemetryReceiverSection:
    bind_host: str = ""
    """Where telemetry is received. Empty: 127.0.0.1 for a platform on loopback, else 0.0.0.0."""
    rate_hz: float = 0.0
    """Datagrams per second asked of platforms. 0: the platform's configured rate."""
    battery_low_v: float = 23.0
    """Low battery warning below this pack voltage (also raised when the platform says LOW)."""
    battery_clear_v: float = 23.4
    """The low battery warning clears at or above this voltage."""
    controller_max_c: float = 70.0
    """Controller over-temperature warning at or above this heatsink temperature."""
    controller_clear_c: float = 65.0
    """The over-temperature warning clears below this temperature."""
    loss_warn_pct: float = 10.0
    """Link degraded when more than this share of recent datagrams was lost."""
    loss_window: int = 50
    """How many recent sequence numbers the loss figure covers (10 s at 5 Hz)."""
    silence_s: float = 1.0
    """Link degraded when no valid datagram arrived for this long."""


@dataclass
class StationMediaSection:
    microphone_device: str = ""
    """ALSA capture device for talking to a platform. Empty: the default."""
    speaker_device: str = ""
    """ALSA playback device for a platform's microphone. Empty: the default."""


@dataclass
class ConsoleSection:
    drive_timeout: float = 0.2
    """A console page's drive input lasts this long unless repeated (it sends at 20 Hz): a
    page that goes quiet stops the robot within this plus one $PVEL period."""
    tls_cert: str = ""
    """PEM certificate (chain) for serving the console and local API over HTTPS as well, for an
    operator on another host (the browser's video decoder needs a secure context: plain HTTP
    qualifies only on 127.0.0.1/localhost). Empty: no HTTPS."""
    tls_key: str = ""
    """PEM private key of ``tls_cert``."""
    https_host: str = "0.0.0.0"
    """Where the HTTPS console listens (with ``tls_cert``)."""
    https_port: int = 8743
    https_names: list[str] = field(default_factory=list)
    """Host names (or addresses) operators open the HTTPS console by, e.g. ["station.local"]:
    any other Host header is refused (DNS rebinding), as on the loopback API."""
    tls_client_ca: str = ""
    """PEM CA bundle: when set, HTTPS clients must present a certificate it signed (the local
    API has no login of its own, and it can move the robot)."""


@dataclass
class StationConfig:
    station: StationSection = field(default_factory=StationSection)
    security: SecuritySection = field(default_factory=SecuritySection)
    discovery: DiscoverySection = field(default_factory=DiscoverySection)
    telemetry: TelemetryReceiverSection = field(default_factory=TelemetryReceiverSection)
    teleop: TeleopSection = field(default_factory=TeleopSection)
    joystick: JoystickSection = field(default_factory=JoystickSection)
    media: StationMediaSection = field(default_factory=StationMediaSection)
    console: ConsoleSection = field(default_factory=ConsoleSection)


# --------------------------------------------------------------------------- loading


def load_config(
    cls: type[C], path: str | Path | None = None, overrides: list[str] | tuple[str, ...] = ()
) -> C:
    """Build ``cls`` from defaults, then the TOML file at ``path``, then ``overrides``."""
    config = cls()
    if path is not None:
        source = str(path)
        try:
            with open(path, "rb") as file:
                data = tomllib.load(file)
        except FileNotFoundError:
            raise ConfigError(f"{source}: file not found") from None
        except OSError as err:
            raise ConfigError(f"{source}: cannot read: {err.strerror}") from None
        except tomllib.TOMLDecodeError as err:
            raise ConfigError(f"{source}: invalid TOML: {err}") from None
        _apply_table(config, data, source, "")
    for item in overrides:
        apply_override(config, item)
    return config


def apply_override(config: object, item: str) -> None:
    """Apply one ``SECTION.KEY=VALUE`` override; VALUE is a TOML value or a bare string."""
    source = f"--set {item}"
    dotted, sep, raw = item.partition("=")
    if not sep or "." not in dotted:
        raise ConfigError(f"{source}: expected SECTION.KEY=VALUE")
    try:
        value: Any = tomllib.loads(f"v = {raw}")["v"]
    except tomllib.TOMLDecodeError:
        value = raw  # bare strings need no quotes on the command line
    table: dict[str, Any] = {}
    cursor = table
    parts = dotted.strip().split(".")
    for part in parts[:-1]:
        cursor = cursor.setdefault(part, {})
    cursor[parts[-1]] = value
    _apply_table(config, table, source, "")


def _apply_table(target: object, data: dict[str, Any], source: str, prefix: str) -> None:
    hints = typing.get_type_hints(type(target))
    known = {f.name for f in dataclasses.fields(target)}  # type: ignore[arg-type]
    for key, value in data.items():
        dotted = f"{prefix}{key}"
        if key not in known:
            kind = "section" if not prefix else "key"
            raise ConfigError(f"{source}: unknown {kind} '{dotted}'")
        expected = hints[key]
        current = getattr(target, key)
        if dataclasses.is_dataclass(current):
            if not isinstance(value, dict):
                raise ConfigError(f"{source}: '{dotted}' must be a table")
            _apply_table(current, value, source, f"{dotted}.")
            continue
        setattr(target, key, _coerce(value, expected, source, dotted))


def _coerce(value: Any, expected: Any, source: str, dotted: str) -> Any:
    origin = typing.get_origin(expected)
    if origin in (types.UnionType, typing.Union):
        options = typing.get_args(expected)
        for option in options:
            try:
                return _coerce(value, option, source, dotted)
            except ConfigError:
                continue
        raise ConfigError(f"{source}: '{dotted}' must be {_type_name(expected)}")
    if expected is type(None):
        if value is None:
            return None
        raise ConfigError(f"{source}: '{dotted}' must be unset")
    if origin is list:
        (item_type,) = typing.get_args(expected)
        if not isinstance(value, list):
            raise ConfigError(f"{source}: '{dotted}' must be a list of {_type_name(item_type)}")
        return [_coerce(item, item_type, source, dotted) for item in value]
    if expected is float and isinstance(value, int) and not isinstance(value, bool):
        return float(value)
    if expected is bool and not isinstance(value, bool):
        raise ConfigError(f"{source}: '{dotted}' must be true or false, not {value!r}")
    if expected is int and isinstance(value, bool):
        raise ConfigError(f"{source}: '{dotted}' must be an integer, not {value!r}")
    if not isinstance(value, expected):
        raise ConfigError(f"{source}: '{dotted}' must be {_type_name(expected)}, not {value!r}")
    return value


def _type_name(expected: Any) -> str:
    names = {str: "a string", int: "an integer", float: "a number", bool: "true or false"}
    return names.get(expected, str(expected))


# --------------------------------------------------------------------------- dumping


def dump_toml(config: object) -> str:
    """The configuration as TOML, every key included, each section with its docstrings."""
    lines: list[str] = []
    for section in dataclasses.fields(config):  # type: ignore[arg-type]
        value = getattr(config, section.name)
        lines.append(f"[{section.name}]")
        docs = _field_docs(type(value))
        for item in dataclasses.fields(value):
            doc = docs.get(item.name)
            if doc:
                lines.extend(f"# {line}" for line in doc.splitlines())
            lines.append(f"{item.name} = {_toml_value(getattr(value, item.name))}")
        lines.append("")
    return "\n".join(lines)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        escaped = value.replace("\\", "\\\\").replace('"', '\\"')
        return f'"{escaped}"'
    if isinstance(value, list):
        return "[" + ", ".join(_toml_value(item) for item in value) + "]"
    raise TypeError(f"cannot write {value!r} as TOML")


def _field_docs(cls: type) -> dict[str, str]:
    """Attribute docstrings (the string literal after a field), read from the source."""
    import ast
    import inspect
    import textwrap

    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except (OSError, TypeError):
        return {}
    docs: dict[str, str] = {}
    body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
    for node, following in itertools.pairwise(body):
        if (
            isinstance(node, ast.AnnAssign)
            and isinstance(node.target, ast.Name)
            and isinstance(following, ast.Expr)
            and isinstance(following.value, ast.Constant)
            and isinstance(following.value.value, str)
        ):
            docs[node.target.id] = inspect.cleandoc(following.value.value)
    return docs
