"""The platform daemon's configuration schema: every section, key, default and constraint.

A key's documentation is the string after it (``brasidas-platform config`` prints it); its
constraints are the checks given to :func:`~brasidas.config.loader.setting`.
"""

from __future__ import annotations

import ipaddress
from dataclasses import dataclass, field
from typing import ClassVar

from brasidas.config.admission import PLATFORM_RENAMED, StrangerAdmissionSection
from brasidas.config.lidar import LidarSection
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
    ip_network,
    non_empty,
    one_of,
    ordered,
    ordered_across,
    remote_port,
    setting,
    url,
)
from brasidas.limits import ANSWER_MAX_BYTES, MAP_REQUEST_MAX_BYTES

BAUD_RATES = (1200, 2400, 4800, 9600, 19200, 38400, 57600, 115200)
H264_ENCODERS = ("v4l2h264enc", "omxh264enc", "x264enc", "openh264enc")
"""The encoders the NavCam pipeline knows, in the order it tries them."""
TEST_PATTERNS = (
    *("smpte", "snow", "black", "white", "red", "green", "blue", "checkers-1", "checkers-2"),
    *("checkers-4", "checkers-8", "circular", "blink", "smpte75", "zone-plate", "gamut"),
    *("chroma-zone-plate", "solid-color", "ball", "smpte100", "bar", "pinwheel", "spokes"),
    *("gradient", "colors", "smpte-rp-219"),
)
"""GStreamer's videotestsrc patterns."""

GPIO_PREFIX = "gpio:"


@dataclass(frozen=True)
class GpioLine:
    """An output on a GPIO line, ``gpio:CHIP:LINE`` in the config (libgpiod's character
    device, never sysfs): ``CHIP`` ``/dev/gpiochip0`` or ``gpiochip0``, ``LINE`` an offset
    (``17``) or a line name (``GPIO17``)."""

    chip: str
    """The character device's path, e.g. ``/dev/gpiochip0``."""
    line: int | str
    """Its offset on the chip, or its name."""

    @classmethod
    def parse(cls, output: str) -> GpioLine:
        """ValueError unless ``output`` is ``gpio:CHIP:LINE``."""
        chip, sep, line = output.removeprefix(GPIO_PREFIX).rpartition(":")
        line = line.strip()
        if not output.startswith(GPIO_PREFIX) or not sep or not chip or not line:
            raise ValueError(f"not gpio:CHIP:LINE: {output!r}")
        if "/" not in chip:
            chip = f"/dev/{chip}"
        if not chip.startswith("/dev/"):
            raise ValueError(f"{chip} is not a GPIO character device (/dev/gpiochipN)")
        return cls(chip, int(line) if line.isdecimal() else line)

    def __str__(self) -> str:
        return f"{self.chip}:{self.line}"


def _gpio_line(value: str) -> bool:
    try:
        GpioLine.parse(value)
    except ValueError:
        return False
    return True


platform_id = Check(
    "1-32 bytes of printable text",
    lambda value: 0 < len(value.encode()) <= 32 and value.isprintable(),
)
"""A beacon (at most 100 bytes) carries the id and the signaling URL."""

lights_output = Check(
    'empty, one controller output letter (e.g. "C") or a GPIO line "gpio:CHIP:LINE" '
    '(e.g. "gpio:/dev/gpiochip0:17"; libgpiod, sysfs paths are not accepted)',
    lambda value: (
        value == ""
        or (len(value) == 1 and value.isascii() and value.isalpha())
        or _gpio_line(value)
    ),
)


@dataclass(frozen=True)
class PlatformSection:
    id: str = setting("brasidas-1", platform_id)
    """Platform id: unique on the network, shown in discovery. At most 32 bytes (UTF-8), so
    that a beacon carrying it stays within its 100 bytes."""
    model: str = "Brasidas UGV"
    max_speed_kmh: float = setting(6.0, above(0, most=100))
    """Top speed at full command (R-2.1), reported to stations."""


@dataclass(frozen=True)
class SecuritySection:
    key_file: str = ""
    """Fleet key path. Empty: $XDG_STATE_HOME/brasidas/fleet.key."""
    insecure: bool = False
    """Run without a fleet key: no beacon HMAC, no authenticated connect. Never in the field."""
    stream_destinations: tuple[str, ...] = setting((), each(ip_network))
    """Where a station may have a stream sent besides its own address and loopback: addresses
    or networks (``198.51.100.7``, ``198.51.100.0/24``, a multicast group). Empty: none — a
    session cannot turn the platform's streams on a third host."""


@dataclass(frozen=True)
class SignalingSection:
    """The signaling server; which connections it holds, and how long, is ``[admission]``."""

    host: str = setting("127.0.0.1", ip_address)
    """Address the signaling server listens on (0.0.0.0: every interface)."""
    port: int = setting(8765, bind_port)
    advertise_host: str = setting("", empty_or(host_name))
    """Host put in the signaling URL of beacons. Empty: ``host``."""
    session_timeout: float = setting(5.0, above(0, most=3600))
    """A session with no heartbeat for this long ends (and releases the manual override) —
    except the override holder's while the failsafe ladder holds for it: the ladder's release
    step (``failsafe.release_after``, ``failsafe.action``) decides, and its session ends after
    the release. Must exceed ``failsafe.hold_after``."""
    heartbeat_interval: float = setting(1.0, at_least(0.05, most=600))
    """How often stations are told to send heartbeats."""
    max_request_bytes: int = setting(MAP_REQUEST_MAX_BYTES, at_least(1024, most=16 * 1024 * 1024))
    """The largest JSON-RPC request (HTTP body or WebSocket message): a map or a route must
    fit (``brasidas.limits.MAP_REQUEST_MAX_BYTES``, what stations send at most)."""
    command_timeout: float = setting(3.0, above(0, most=60))
    """How long a system command may take to be answered by its actor."""
    max_answer_bytes: int = setting(ANSWER_MAX_BYTES, at_least(65536, most=1 << 26))
    """An answer longer than this is replaced by an error (``get_map`` sends a map of up to
    ``max_request_bytes`` back: ``brasidas.limits.ANSWER_MAX_BYTES``)."""


@dataclass(frozen=True)
class BeaconSection:
    RULES: ClassVar[tuple[Rule, ...]] = (ordered("min_interval", "max_interval"),)

    enabled: bool = True
    port: int = setting(21000, remote_port)
    destinations: tuple[str, ...] = setting(("127.255.255.255",), non_empty, each(ip_address))
    """Where beacons go: broadcast, multicast group (R-0.6.1) or unicast addresses. The default
    is the loopback broadcast; deployments name the mesh's broadcast address or a group."""
    min_interval: float = setting(0.6, at_least(0.05, most=60))
    max_interval: float = setting(3.0, at_least(0.05, most=3600))
    move_threshold_m: float = setting(1.0, at_least(0, most=10000))
    interface_host: str = setting("127.0.0.1", ip_address)
    """Local address beacons are sent from (picks the interface, multicast ones included)."""
    multicast_ttl: int = setting(1, at_least(1, most=255))
    """Hops a beacon to a multicast destination may cross: 1 stays on the segment; a routed
    mesh (OLSR, BATMAN at layer 3) needs its diameter."""
    listen: bool = True
    """Keep the list of the other platforms online from their beacons (R-9): list_platforms."""
    listen_host: str = setting("0.0.0.0", ip_address)
    """Where this platform hears the others' beacons (on ``port``; it joins the multicast
    destinations on the interface of ``interface_host``)."""
    expiry: float = setting(4.0, above(0, most=3600))
    """Another platform is dropped from the list this long after its last beacon."""


@dataclass(frozen=True)
class MotorSection:
    enabled: bool = True
    port: str = setting("/dev/ttyUSB0", non_empty)
    """Serial device of the AX3500. In --sim, the simulator's pty is opened instead."""
    baudrate: int = setting(9600, one_of(*BAUD_RATES))
    bytesize: int = setting(7, one_of(5, 6, 7, 8))
    parity: str = setting("E", one_of("N", "E", "O", "M", "S"))
    stopbits: int = setting(1, one_of(1, 2))
    linear_scale: float = setting(1.0, fraction)
    """Fraction of full power (7F) that linear x = 1 commands on channel 1 (a gentler robot)."""
    angular_scale: float = setting(1.0, fraction)
    """Fraction of full power that angular z = 1 commands on channel 2."""
    linear_limit: float = setting(1.0, fraction)
    """Hard cap on channel 1 after scaling, as a fraction of full power."""
    angular_limit: float = setting(1.0, fraction)
    """Hard cap on channel 2 after scaling, as a fraction of full power."""
    invert_linear: bool = False
    """Channel 1 forward drives this chassis backwards (wiring)."""
    invert_angular: bool = False
    """False: a left turn (positive angular z) is !B; true when !b turns left (wiring)."""
    refresh_hz: float = setting(10.0, at_least(2, most=50))
    """Resend the commanded velocity this often even when unchanged (the watchdog needs >= 2)."""
    poll_hz: float = setting(1.0, at_least(0, most=20))
    """Status polls (?e battery, ?m heatsinks, ?a amps) per second; 0: never."""
    reply_timeout: float = setting(0.3, above(0, most=10))
    """Seconds to wait for a command's echo and answer."""
    max_unanswered: int = setting(3, at_least(1, most=100))
    """Consecutive unanswered commands after which the controller counts as gone (reconnect)."""
    configure_mode: bool = False
    """When the controller is not in RS-232-with-watchdog, mixed open-loop mode, write those
    settings to its flash and reset it. False (the default: never rewrite a controller's stored
    setup unasked): a wrong motor mode refuses to drive, with the reason (the input mode warns)."""
    reconnect_max: float = setting(5.0, above(0, most=300))
    """Longest wait between attempts to reopen a missing or silent controller (backoff cap)."""
    main_lights_output: str = setting("C", lights_output)
    """Main lights (10.6): a controller output letter, or "gpio:CHIP:LINE", a line driven
    through libgpiod (e.g. "gpio:/dev/gpiochip0:17": offset 17, or "gpio:gpiochip0:GPIO17")."""
    positional_lights_output: str = setting("", lights_output)
    """Positional lights (10.7), as main_lights_output. Empty: not fitted, 10.7 is refused
    (in --sim: line 17 of a simulated /dev/gpiochip0)."""


@dataclass(frozen=True)
class VelocitySection:
    host: str = setting("127.0.0.1", ip_address)
    """Where the platform listens for $PVEL datagrams."""
    port: int = setting(21001, bind_port)
    advertise_host: str = setting("", empty_or(host_name))
    """Host given to stations by get_velocity_connection_info. Empty: ``host``."""
    deadman: float = setting(0.3, at_least(0.02, most=10))
    """In teleop, no valid velocity for this long commands zero."""
    stats_interval: float = setting(1.0, at_least(0.1, most=60))
    """How often the receiver's counters are published for telemetry (when they changed)."""
    max_age_ms: float = setting(500.0, above(0, most=10000))
    """A velocity packet older than this on arrival (by its send time) is dropped and counted
    (``stale``): a burst of stale commands after a lag spike never moves the robot."""


@dataclass(frozen=True)
class FailsafeSection:
    """The failsafe ladder while teleoperated (issue 13): zero after ``velocity.deadman``,
    hold after ``hold_after``, release (or keep holding) after ``release_after``."""

    RULES: ClassVar[tuple[Rule, ...]] = (ordered("hold_after", "release_after"),)

    hold_after: float = setting(1.5, at_least(0.05, most=60))
    """No call (heartbeat) from the override holder for this long: hold (motors zero,
    payload safe, velocities dropped until the operator re-engages)."""
    release_after: float = setting(10.0, above(0, most=3600))
    """Silent this long: ``action``. The holder's session does not time out
    (``signaling.session_timeout``) while the ladder holds: this step, not the session's
    expiry, releases the override."""
    action: str = setting("release", one_of("release", "hold"))
    """At ``release_after``: release the override (autonomy resumes) or keep holding."""
    gcs_loss_action: str = setting("continue", one_of("continue", "hold"))
    """The controlling station's or ground station's session lost while patrolling: the
    patrol goes on, or holds (stopped, until an operator starts it): ArduPilot's FS_GCS_ENABLE."""


@dataclass(frozen=True)
class SafetySection:
    """The teleop speed cap that follows the measured latency (issue 13, R-11.5)."""

    stop_distance_m: float = setting(1.0, above(0, most=100))
    """The robot must stop within this after the operator sees a reason to."""
    reaction_s: float = setting(0.25, at_least(0, most=10))
    """The operator's reaction time (the seed's 250 ms); 10 s at most (a larger one is a typo,
    and the cap would round to zero or overflow)."""
    braking_mps2: float = setting(4.2, at_least(0.1, most=50))
    """Deceleration when stopping. 4.2 m/s² is what makes the seed's budget exact: 6 km/h
    stops within 1 m after 250 ms reaction and 150 ms video latency."""
    worst_latency_ms: float = setting(400.0, at_least(0, most=60000))
    """Video plus command latency assumed without a report from the override holder."""
    report_max_age_s: float = setting(5.0, above(0, most=600))
    """A latency report older than this no longer counts (the worst is assumed)."""


@dataclass(frozen=True)
class PayloadSection:
    """Payloads (issue 13): each a set of actors on command groups 100-110."""

    enabled: tuple[str, ...] = setting((), each(one_of("turret")))
    """The payloads this platform carries, by name; none by default."""
    turret_port: str = setting("/dev/ttyUSB1", non_empty)
    """The turret microcontroller's serial line (in --sim, the simulator's pty instead)."""
    turret_baudrate: int = setting(115200, one_of(*BAUD_RATES))
    turret_ack_timeout: float = setting(0.1, above(0, most=5))
    """How long the driver waits for an acknowledgement before it resends (3 tries)."""
    turret_watchdog_s: float = setting(0.5, above(0, most=10))
    """The microcontroller releases the trigger when no valid command came for this long; the
    driver pings at a third of it."""
    turret_stream: str = setting("payload_camera", one_of("", "payload_camera"))
    """The turret's sight, registered as its stream (connect's capabilities, telemetry): the
    thermal IP camera of [payload_camera], when that is enabled. Empty: the turret has none."""


@dataclass(frozen=True)
class GpsSection:
    enabled: bool = True
    port: str = setting("/dev/ttyAMA0", non_empty)
    """Serial device of the NMEA receiver (8N1). In --sim, the simulator's pty is read instead
    (unless this names another device)."""
    baudrate: int = setting(9600, one_of(*BAUD_RATES))
    fix_timeout: float = setting(3.0, above(0, most=600))
    """Seconds without a fix (receiver silent or port gone) before the fix is reported lost."""
    sim_rate_hz: float = setting(1.0, at_least(1, most=10))
    """Epochs per second of the simulated receiver (1-10; the NEO-6M defaults to 1)."""


@dataclass(frozen=True)
class ImuSection:
    enabled: bool = True
    i2c_bus: int = setting(1, at_least(0, most=255))
    """I2C bus number (/dev/i2c-N); the Raspberry Pi header is bus 1."""
    address: int = setting(0x68, one_of(0x68, 0x69))
    """0x68 (104) with AD0 low, 0x69 (105) with AD0 high."""
    rate_hz: float = setting(100.0, at_least(4, most=1000))
    """Samples read (and fused) per second (the chip's divider of 1 kHz: 4-1000)."""
    fifo: bool = True
    """Let the chip queue samples in its FIFO and drain it ~10 times a second (a tenth of the
    wake-ups); false reads one 14-byte burst per sample, waking at rate_hz."""
    accel_range_g: int = setting(2, one_of(2, 4, 8, 16))
    """Accelerometer full scale: 2, 4, 8 or 16 g (ACCEL_CONFIG AFS_SEL)."""
    gyro_range_dps: int = setting(250, one_of(250, 500, 1000, 2000))
    """Gyro full scale: 250, 500, 1000 or 2000 deg/s (GYRO_CONFIG FS_SEL)."""
    madgwick_beta: float = setting(0.05, above(0, most=1))
    """Madgwick filter gain: higher trusts the accelerometer more (faster, noisier)."""
    calibrate_s: float = setting(1.0, at_least(0, most=60))
    """Seconds of stillness at start used to measure the gyro's zero-rate offset (0: off)."""


@dataclass(frozen=True)
class TelemetrySection:
    RULES: ClassVar[tuple[Rule, ...]] = (ordered("battery_low_v", "battery_high_v"),)

    rate_hz: float = setting(5.0, at_least(0.1, most=50))
    """Datagrams per second pushed to a station that asked (request_telemetry)."""
    battery_low_v: float = setting(23.0, above(0, most=100))
    """Pack voltage below which the coarse battery level is LOW (24 V lead-acid pack)."""
    battery_high_v: float = setting(25.0, above(0, most=100))
    """Pack voltage at or above which the coarse level is HIGH; MEDIUM in between."""
    battery_monitor: bool = True
    """Report the coarse battery level when the controller's status has no 20.4 monitor flag."""


@dataclass(frozen=True)
class NavCamSection:
    RULES: ClassVar[tuple[Rule, ...]] = (ordered("idle_framerate", "framerate", strict=False),)

    enabled: bool = True
    device: str = setting("/dev/video0", non_empty)
    width: int = setting(640, at_least(16, most=4096))
    height: int = setting(480, at_least(16, most=4096))
    framerate: int = setting(30, at_least(1, most=30))
    idle_framerate: int = setting(5, at_least(1, most=30))
    """Framerate while the manual override is disengaged (seed ch. 10 §3.2)."""
    bitrate_kbps: int = setting(1500, at_least(50, most=50000))
    """H.264 bitrate; 1500 keeps 640x480@30 moving content under the seed's 1.6 Mbit/s."""
    port: int = setting(5600, remote_port)
    """UDP port on the station that the NavCam RTP stream is sent to."""
    format: str = setting("raw", one_of("raw", "mjpeg"))
    """What the camera delivers at width x height @ framerate: "raw" or "mjpeg"."""
    encoder: str = setting("", one_of("", *H264_ENCODERS))
    """Force an H.264 encoder (v4l2h264enc, omxh264enc, x264enc, openh264enc). Empty: first found."""
    sim_pattern: str = setting("ball", one_of(*TEST_PATTERNS))
    """--sim source: a videotestsrc pattern (ball moves; smpte with sim_motion for bandwidth)."""
    sim_motion: int = setting(0, at_least(0, most=1000))
    """--sim source: videotestsrc horizontal-speed (pixels per frame); 0 for a still pattern."""
    intra_refresh: bool = False
    """Refresh the picture by a sweep of intra blocks each second instead of a keyframe each
    second (x264enc): no keyframe bursts; a keyframe request starts a new sweep instead of an
    IDR. The station's receive/view follow it; the console page's feed still needs IDRs, so
    it is off by default."""
    fec_max_percent: int = setting(0, at_least(0, most=100))
    """Most forward error correction (ULPFEC) overhead on the NavCam, in percent of its
    packets; the share follows the loss the stations report, within the bitrate. 0 (the
    default): none. For links whose round trip is too long for retransmission: on a short
    one, a lost FEC packet holds the complete frames behind it in the receiver's jitter
    buffer until it is repaired (measured: glass-to-glass p99 over 300 ms at 5 % loss)."""


@dataclass(frozen=True)
class AudioSection:
    enabled: bool = True
    """Two-way audio: platform microphone to the station, station microphone to the speaker."""
    source_device: str = ""
    """ALSA capture device (e.g. hw:1,0). Empty: the default. In --sim: a test tone."""
    sink_device: str = ""
    """ALSA playback device. Empty: the default. In --sim: discarded (fakesink)."""
    bitrate: int = setting(24000, at_least(6000, most=510000))
    """Opus bitrate (bit/s) of the platform microphone."""
    out_port: int = setting(5602, remote_port)
    """UDP port on the station that the platform microphone is sent to."""
    in_host: str = setting("127.0.0.1", ip_address)
    """Where the platform listens for the station's audio (the mesh address in deployments)."""
    in_port: int = setting(5604, bind_port)
    """UDP port the platform listens on for the station's audio."""


@dataclass(frozen=True)
class PayloadCameraSection:
    RULES: ClassVar[tuple[Rule, ...]] = (
        Rule(
            "url",
            "an rtsp URL when enabled",
            lambda s: not s.enabled or url("rtsp", "rtsps").ok(s.url),
            ("enabled",),
        ),
    )

    enabled: bool = False
    """The payload IP camera (the seed's thermal AXIS), forwarded without re-encoding."""
    url: str = setting("", empty_or(url("rtsp", "rtsps")))
    """RTSP URL of the camera, e.g. rtsp://192.168.1.90/axis-media/media.amp."""
    port: int = setting(5606, remote_port)
    """UDP port on the station that the camera's RTP stream is forwarded to."""
    latency_ms: int = setting(50, at_least(0, most=10000))
    """rtspsrc jitter buffer (the camera's own network hop)."""


@dataclass(frozen=True)
class SimSection:
    enabled: bool = False
    """Set by --sim: simulated controller, GPS, IMU and camera behind the real drivers."""
    latitude: float = setting(37.9415, at_least(-90, most=90))
    """Where the simulated vehicle starts (degrees, WGS-84)."""
    longitude: float = setting(23.6530, at_least(-180, most=180))
    altitude_m: float = setting(42.0, at_least(-500, most=9000))
    heading_deg: float = setting(0.0, at_least(0, most=360))
    """Compass heading at start (clockwise from north)."""
    demo_map: bool = True
    """Load the demo map and route when none is stored (false: a teleop-only rover, no map)."""
    gps_receiver: str = setting("neo6m", one_of("neo6m", "rtk"))
    """The simulated GPS receiver's error: "neo6m" (the rover's u-blox NEO-6M, 2.5 m CEP
    wandering over minutes) or "rtk" (an RTK-corrected u-blox ZED-F9P class, 0.02 m per axis;
    pair it with autonomy.gps_sigma_m = 0.02, autonomy.gps_jitter_m = 0.02)."""
    obstacles_file: str = ""
    """Obstacles the map does not have, known to the simulated lidar only (issue 30): GeoJSON
    polygons, and Points with a ``radius_m`` property; ``"material": "glass"`` is not seen."""
    carmen_file: str = ""
    """A recorded 2-D scan log in CARMEN format (FLASER, ROBOTLASER1 lines) the simulated
    lidar replays once at the log's pace instead of seeing the simulated world (then it is
    silent: the platform stops for a blind lidar). The log's odometry is not used here."""
    pedestrians: int = setting(0, at_least(0, most=100))
    """People (0.3 m discs) walking back and forth at 1.2 m/s near the start, for the lidar."""
    lux: float = setting(0.0, at_least(0, most=150000))
    """Ambient light on the simulated lidar: sunlight (~100,000 lux) thins and shortens its
    returns."""
    seed: int = setting(1, at_least(0, most=2**31))
    """Seeds the simulated lidar's noise and pedestrians (reproducible runs)."""


@dataclass(frozen=True)
class AutonomySection:
    enabled: bool = True
    """The patrol automation is on at start (command 10.8 switches it live)."""
    autostart: bool = True
    """Patrol the stored route at start (Scenario #2); the --sim demo route never starts itself."""
    route_file: str = ""
    """Where the waypoints are kept across restarts. Empty: $XDG_STATE_HOME/brasidas/route.json."""
    cruise_speed_kmh: float = setting(6.0, above(0, most=100))
    """Patrol speed on straight legs (capped by platform.max_speed_kmh)."""
    max_turn_rate_dps: float = setting(60.0, above(0, most=720))
    """Turn-rate limit while patrolling (degrees per second)."""
    full_turn_rate_dps: float = setting(86.0, above(0, most=720))
    """The platform's turn rate at angular = 1 (degrees per second)."""
    lookahead_m: float = setting(2.0, above(0, most=100))
    """Pure pursuit's look-ahead distance."""
    arrival_tolerance_m: float = setting(0.5, above(0, most=100))
    """A waypoint within this distance is reached."""
    decel_mps2: float = setting(0.5, above(0, most=20))
    """How hard the robot slows down toward a waypoint."""
    clearance_m: float = setting(4.5, at_least(0, most=100))
    """Planned paths keep at least this far from keep-out zones and the boundary. It must cover
    the localization's error across the path, or the true robot enters what its pose avoids:
    with a NEO-6M (``gps_sigma_m`` 2.1 m per axis, wandering over minutes, which no filter
    removes) 2 sigma is 4.2 m, plus ~0.3 m of the follower's tracking error: the robot stays
    out about 98 % of the time. A better receiver (SBAS, RTK) earns a smaller one."""
    corridor_m: float = setting(3.0, above(0, most=1000))
    """Further than this from the planned path: replan from where the robot is."""
    fix_stale_s: float = setting(2.0, above(0, most=60))
    """Hold when the last GPS fix is older than this."""
    rate_hz: float = setting(10.0, at_least(2, most=50))
    """cmd_vel and pose rate (the controller's watchdog needs >= 2)."""
    gps_sigma_m: float = setting(2.1, above(0, most=100))
    """Localization: a fix's absolute position error at HDOP 1, one axis, 1 sigma (the NEO-6M's
    2.5 m CEP). It wanders over minutes, so no filter removes it: it sizes the pose's
    uncertainty (and ``clearance_m``), not the weight of a fix."""
    gps_jitter_m: float = setting(0.5, above(0, most=100))
    """Localization: fix-to-fix position noise at HDOP 1, what a fix is weighted by."""


@dataclass(frozen=True)
class MapSection:
    file: str = ""
    """The area map (GeoJSON, R-12). Empty: $XDG_STATE_HOME/brasidas/map.geojson."""


def _is_loopback(host: str) -> bool:
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def _udp_target(value: str) -> bool:
    host, sep, port = value.rpartition(":")
    return bool(sep) and port.isdecimal() and 1 <= int(port) <= 65535 and ip_address.ok(host)


@dataclass(frozen=True)
class MavlinkSection:
    """The MAVLink 2 endpoint for ground control stations (docs/integrations.md, "Ground control
    stations")."""

    RULES: ClassVar[tuple[Rule, ...]] = (
        Rule(
            "allow_unsigned_control",
            "false unless {section}.host is loopback or "
            "{section}.unsigned_control_off_loopback_i_accept_the_risk is true (anyone who can "
            "send the endpoint a datagram could then drive the robot: docs/integrations.md, Signing)",
            lambda s: (
                not s.allow_unsigned_control
                or _is_loopback(s.host)
                or s.unsigned_control_off_loopback_i_accept_the_risk
            ),
            ("host", "unsigned_control_off_loopback_i_accept_the_risk"),
        ),
    )

    enabled: bool = False
    """Speak MAVLink 2 to QGroundControl, Mission Planner, MAVProxy and MAVSDK."""
    system_id: int = setting(1, at_least(1, most=254))
    """This vehicle's MAVLink system id (255 is the ground stations' usual one)."""
    host: str = setting("127.0.0.1", ip_address)
    """Address the endpoint listens on (0.0.0.0: every interface, for a GCS on the mesh)."""
    port: int = setting(0, bind_port)
    """UDP port it listens on (0: any free port; ground stations answer the source port)."""
    targets: tuple[str, ...] = setting(("127.0.0.1:14550",), each(Check("HOST:PORT", _udp_target)))
    """Where telemetry is sent unasked (14550: QGroundControl's listening port). Any other
    station that talks to the endpoint is answered and sent telemetry while it is heard."""
    link_timeout: float = setting(10.0, above(0, most=3600))
    """A station not in ``targets`` is forgotten this long after its last message."""
    upload_window: int = setting(16, at_least(1, most=32))
    """Mission items requested ahead during an upload: a lossy 100 ms link moves a 100-item
    mission in ~2 s instead of ~15 s. 1 is the one-at-a-time protocol of ArduPilot and PX4,
    for a ground station that answers only the request it expects (MAVProxy, MAVSDK and
    pymavlink answer every request; QGroundControl is not tested here)."""
    heartbeat_hz: float = setting(1.0, above(0, most=10))
    """HEARTBEAT of the vehicle and of the camera component."""
    position_hz: float = setting(5.0, above(0, most=50))
    """GLOBAL_POSITION_INT, GPS_RAW_INT, ATTITUDE, VFR_HUD."""
    status_hz: float = setting(1.0, above(0, most=10))
    """SYS_STATUS, BATTERY_STATUS, MISSION_CURRENT; HOME_POSITION at a fifth of this."""
    signing_key_file: str = ""
    """MAVLink 2 signing passphrase (one line; key = SHA-256 of it, as MAVProxy's ``signing
    setup`` and QGroundControl). Owner-only like the fleet key. Empty: no signing."""
    signing_state_file: str = ""
    """The signing clock and replay table, kept across restarts so a captured session never
    replays. Empty: $XDG_STATE_HOME/brasidas/mavlink-signing.json."""
    allow_unsigned_control: bool = False
    """With signing configured: let unsigned links change the robot (modes, missions, fences,
    joystick). Anyone who can send a UDP datagram to the endpoint could then drive it: refused
    unless ``host`` is loopback or the next key is set."""
    unsigned_control_off_loopback_i_accept_the_risk: bool = False
    """Let ``allow_unsigned_control`` work on a non-loopback ``host``: every consequence is in
    docs/integrations.md (Signing); never on a mesh others can reach."""
    camera: bool = True
    """Announce the NavCam as a MAVLink camera component (id 100) with its video stream."""
    skip_unsupported: bool = False
    """Mission uploads: leave out the items a rover cannot do (each named in the upload's
    answer) instead of refusing the mission."""
    parameters_file: str = ""
    """The parameters ground stations set (``FENCE_OPTIONS``: 2 takes several uploaded inclusion
    fences as their union), kept across restarts. Empty:
    $XDG_STATE_HOME/brasidas/mavlink-parameters.json."""


@dataclass(frozen=True)
class RecorderSection:
    """The on-board recorder (issue 23): MCAP files of telemetry, commands and the NavCam."""

    enabled: bool = True
    dir: str = ""
    """Where recordings are written. Empty: $XDG_STATE_HOME/brasidas/recordings."""
    rotate_minutes: float = setting(10.0, above(0, most=1440))
    """A new file is started after this long (at the NavCam's next keyframe)."""
    chunk_seconds: float = setting(1.0, above(0, most=10))
    """A chunk is closed (compressed, written and synced) at least this often: what a power
    cut can lose."""
    max_bytes: int = setting(2 * 1024**3, at_least(1024 * 1024, most=2**50))
    """The recordings' total size; the oldest files are deleted past it."""
    keep_days: float = setting(30.0, above(0, most=3650))
    """Files older than this are deleted."""
    min_free_bytes: int = setting(256 * 1024**2, at_least(0, most=2**50))
    """Free space kept on the recordings' disk: old files go first, then recording stops."""
    queue_messages: int = setting(2000, at_least(16, most=1_000_000))
    """Messages waiting for the writer thread at most; past it new ones are dropped (counted)."""
    telemetry_hz: float = setting(2.0, above(0, most=50))
    """How often every telemetry section is recorded."""
    download_kib_s: int = setting(2048, at_least(0, most=10**7))
    """Every recording download together is sent at most this fast (KiB/s; 0: no limit): a
    station fetching recordings leaves the link's rest to video and control."""
    video_fps: int = setting(5, at_least(0, most=30))
    """The NavCam's rate while no station watches: the recorder's own copy, from the same
    encoder (0: the camera is recorded only while a station watches)."""


@dataclass(frozen=True)
class ArmingSection:
    """Arming and pre-arm checks, the operator's last word kept on disk (issue 27)."""

    state_file: str = ""
    """The operator's last word (start, stop, hold, disarm) across restarts. Empty:
    $XDG_STATE_HOME/brasidas/last_word.json."""
    countdown_s: float = setting(10.0, at_least(0, most=600))
    """Autostart: announced this long before the platform arms itself and patrols."""
    check_gps: bool = True
    """Pre-arm: a GPS fix (when the GPS is enabled)."""
    check_clock: bool = True
    """Pre-arm: the wall clock is set (not before 2024)."""
    check_recorder: bool = True
    """Pre-arm: the recorder can write (when it is enabled)."""


@dataclass(frozen=True)
class PlatformConfig:
    RULES: ClassVar[tuple[Rule, ...]] = (
        ordered_across(
            "failsafe.hold_after",
            "signaling.session_timeout",
            "a silent override holder's session would end before the failsafe ladder holds",
        ),
        ordered_across(
            "lidar.body_radius_m",
            "lidar.clearance_m",
            "an obstacle the robot stopped for would vanish into its own body's blind zone",
        ),
    )
    RENAMED: ClassVar[dict[str, str]] = PLATFORM_RENAMED

    platform: PlatformSection = field(default_factory=PlatformSection)
    security: SecuritySection = field(default_factory=SecuritySection)
    signaling: SignalingSection = field(default_factory=SignalingSection)
    admission: StrangerAdmissionSection = field(default_factory=StrangerAdmissionSection)
    beacon: BeaconSection = field(default_factory=BeaconSection)
    motor: MotorSection = field(default_factory=MotorSection)
    velocity: VelocitySection = field(default_factory=VelocitySection)
    failsafe: FailsafeSection = field(default_factory=FailsafeSection)
    payload: PayloadSection = field(default_factory=PayloadSection)
    safety: SafetySection = field(default_factory=SafetySection)
    gps: GpsSection = field(default_factory=GpsSection)
    imu: ImuSection = field(default_factory=ImuSection)
    telemetry: TelemetrySection = field(default_factory=TelemetrySection)
    navcam: NavCamSection = field(default_factory=NavCamSection)
    audio: AudioSection = field(default_factory=AudioSection)
    payload_camera: PayloadCameraSection = field(default_factory=PayloadCameraSection)
    sim: SimSection = field(default_factory=SimSection)
    autonomy: AutonomySection = field(default_factory=AutonomySection)
    map: MapSection = field(default_factory=MapSection)
    mavlink: MavlinkSection = field(default_factory=MavlinkSection)
    recorder: RecorderSection = field(default_factory=RecorderSection)
    arming: ArmingSection = field(default_factory=ArmingSection)
    lidar: LidarSection = field(default_factory=LidarSection)
