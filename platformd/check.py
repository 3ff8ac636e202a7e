"""``brasidas-platform check``: the bring-up check a team runs first on a new robot (issue 27).

Each configured device is opened and asked to answer as itself: the AX3500's controller id on
the motor port (at the configured baud, then the other plausible ones), NMEA sentences on the
GPS port (and at which baud), the MPU-6050's WHO_AM_I on the I2C bus, the camera's device and
the H.264 encoder GStreamer will use, the GPIO chips of the lights, the fleet and MAVLink
signing keys' permissions, the recorder's free disk, the clock. Each result is one line, with
a one-line fix when it fails; the exit status is 1 when any check fails. Blocking I/O: this
runs as its own command, never inside the daemon's event loop.
"""

from __future__ import annotations

import functools
import json
import os
import shutil
import sys
import termios
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from brasidas import security
from brasidas.codecs import ax3500
from brasidas.codecs.nmea import NmeaDecoder
from brasidas.config import PlatformConfig
from brasidas.config.platform import GPIO_PREFIX, GpioLine
from platformd.arming import CLOCK_SET_AFTER, LastWordStore

if TYPE_CHECKING:
    import serial

PROBE_S = 0.6
"""How long the AX3500 is given to answer at one baud."""
LISTEN_S = 2.5
"""How long the GPS port is listened to at one baud (a receiver talks at least at 1 Hz)."""
WHO_AM_I = 0x75
MPU6050_ID = 0x68


@dataclass(frozen=True)
class CheckResult:
    name: str
    ok: bool
    detail: str
    fix: str = ""


def run_checks(config: PlatformConfig, *, listen_s: float = LISTEN_S) -> list[CheckResult]:
    """Every check that applies to ``config``, in order; the GPS port is listened to for
    ``listen_s`` at each baud."""
    checks: list[Callable[[PlatformConfig], CheckResult | None]] = [
        check_motor,
        functools.partial(check_gps, listen_s=listen_s),
        check_imu,
        check_camera,
        check_gpio,
        check_fleet_key,
        check_signing_key,
        check_disk,
        check_clock,
        check_last_word,
    ]
    results = []
    for check in checks:
        result = check(config)
        if result is not None:
            results.append(result)
    return results


def main(config: PlatformConfig, *, as_json: bool, listen_s: float = LISTEN_S) -> int:
    """Print the results (one line each, or JSON); 1 when any failed."""
    results = run_checks(config, listen_s=listen_s)
    if as_json:
        print(json.dumps([asdict(result) for result in results], indent=2))
    else:
        for result in results:
            print(f"{'ok  ' if result.ok else 'FAIL'} {result.name:<12} {result.detail}")
            if not result.ok and result.fix:
                print(f"     {'':<12} fix: {result.fix}")
    failed = [result.name for result in results if not result.ok]
    if not as_json:
        print(f"{len(results) - len(failed)}/{len(results)} checks passed", file=sys.stderr)
    return 1 if failed else 0


# --------------------------------------------------------------------------- devices


def _open_serial(
    path: str, baudrate: int, bytesize: int, parity: str, stopbits: int
) -> serial.Serial:
    import serial

    return serial.Serial(
        path,
        baudrate=baudrate,
        bytesize=bytesize,
        parity=parity,
        stopbits=stopbits,
        timeout=0.05,
    )


def _missing_port(name: str, path: str, key: str) -> CheckResult | None:
    if os.path.exists(path):
        return None
    return CheckResult(
        name,
        False,
        f"{path} does not exist",
        f"plug the device in, or set {key} to its port (ls /dev/serial/by-id/)",
    )


def _plausible(configured: int) -> list[int]:
    return [configured, *(rate for rate in (9600, 115200, 19200, 4800) if rate != configured)]


def check_motor(config: PlatformConfig) -> CheckResult | None:
    motor = config.motor
    if not motor.enabled:
        return None
    if config.sim.enabled:
        return CheckResult("motor", True, "simulated (--sim): the simulator stands in")
    missing = _missing_port("motor", motor.port, "motor.port")
    if missing is not None:
        return missing
    heard = b""
    for baud in _plausible(motor.baudrate):
        try:
            reply, raw = _ax3500_probe(motor.port, baud, motor.bytesize, motor.parity)
        except termios.error:
            continue  # this baud or framing cannot be set on the port (a pty)
        except OSError as exc:
            return CheckResult("motor", False, f"{motor.port}: {exc}", _permission_fix(exc))
        heard += raw
        if reply is not None:
            ident = reply.values[0] if reply.values else 0
            says = "AX3500" if ident & ax3500.CONTROLLER_ID_AX3500_BIT else f"id {ident:02X}"
            if baud != motor.baudrate:
                return CheckResult(
                    "motor",
                    False,
                    f"{motor.port}: the controller answers at {baud} baud, not {motor.baudrate}",
                    f"set motor.baudrate = {baud}",
                )
            return CheckResult("motor", True, f"{motor.port} at {baud} baud: {says} answers")
    what = _what_it_was(heard)
    return CheckResult(
        "motor",
        False,
        f"{motor.port}: no AX3500 answer at {', '.join(map(str, _plausible(motor.baudrate)))}"
        f" baud{what}",
        "check motor.port (the AX3500's RS-232 port), its cable and that it is in RS-232 mode",
    )


def _ax3500_probe(
    path: str, baud: int, bytesize: int, parity: str
) -> tuple[ax3500.Reply | None, bytes]:
    """Ask the controller id (config ``^8A``); its reply, or None, and what was heard."""
    port = _open_serial(path, baud, bytesize, parity, 1)
    heard = bytearray()
    try:
        command = ax3500.config_read(ax3500.PARAM_CONTROLLER_ID)
        parser, exchange = ax3500.LineParser(), ax3500.Exchange(command)
        port.reset_input_buffer()
        port.write(b"\r" + command.encode())
        deadline = time.monotonic() + PROBE_S
        while time.monotonic() < deadline:
            data = port.read(256)
            heard += data
            for line in parser.feed(data):
                reply = exchange.feed_line(line)
                if reply is not None:
                    return reply, bytes(heard)
        return None, bytes(heard)
    finally:
        port.close()


def _what_it_was(heard: bytes) -> str:
    if b"$GP" in heard or b"$GN" in heard:
        return " (it sends NMEA sentences: that is a GPS receiver)"
    if heard:
        return f" (it sent {len(heard)} bytes of something else)"
    return " (silent)"


def check_gps(config: PlatformConfig, listen_s: float = LISTEN_S) -> CheckResult | None:
    gps = config.gps
    if not gps.enabled:
        return None
    if config.sim.enabled:
        return CheckResult("gps", True, "simulated (--sim): the simulator stands in")
    missing = _missing_port("gps", gps.port, "gps.port")
    if missing is not None:
        return missing
    for baud in _plausible(gps.baudrate):
        try:
            port = _open_serial(gps.port, baud, 8, "N", 1)
        except termios.error:
            continue
        except OSError as exc:
            return CheckResult("gps", False, f"{gps.port}: {exc}", _permission_fix(exc))
        decoder = NmeaDecoder()
        try:
            deadline = time.monotonic() + listen_s
            while time.monotonic() < deadline and decoder.sentences < 3:
                decoder.feed(port.read(512))
        finally:
            port.close()
        if decoder.sentences:
            kinds = ", ".join(sorted(decoder.by_type))
            if baud != gps.baudrate:
                return CheckResult(
                    "gps",
                    False,
                    f"{gps.port}: NMEA at {baud} baud, not {gps.baudrate}",
                    f"set gps.baudrate = {baud}",
                )
            return CheckResult("gps", True, f"{gps.port} at {baud} baud: NMEA ({kinds})")
    return CheckResult(
        "gps",
        False,
        f"{gps.port}: no NMEA sentence in {listen_s:g} s at any plausible baud",
        "check gps.port (the receiver's UART), its wiring (TX to RX) and its power",
    )


def check_imu(config: PlatformConfig) -> CheckResult | None:
    imu = config.imu
    if not imu.enabled:
        return None
    if config.sim.enabled:
        return CheckResult("imu", True, "simulated (--sim): the simulator stands in")
    device = f"/dev/i2c-{imu.i2c_bus}"
    if not os.path.exists(device):
        return CheckResult(
            "imu",
            False,
            f"{device} does not exist",
            "enable I2C (dtparam=i2c_arm=on in config.txt) or set imu.i2c_bus",
        )
    try:
        from smbus2 import SMBus

        with SMBus(imu.i2c_bus) as bus:
            ident = bus.read_byte_data(imu.address, WHO_AM_I)
    except OSError as exc:
        return CheckResult(
            "imu",
            False,
            f"{device} address 0x{imu.address:02X}: {exc}",
            "check the MPU-6050's wiring and imu.address (0x68, or 0x69 with AD0 high)",
        )
    if ident != MPU6050_ID:
        return CheckResult(
            "imu", False, f"WHO_AM_I 0x{ident:02X}, not 0x68", "this is not an MPU-6050"
        )
    return CheckResult("imu", True, f"{device} 0x{imu.address:02X}: MPU-6050 answers")


def check_camera(config: PlatformConfig) -> CheckResult | None:
    navcam = config.navcam
    if not navcam.enabled:
        return None
    try:
        from brasidas.media.gst import MediaError
        from brasidas.media.video import choose_encoder

        encoder = choose_encoder(navcam.encoder)
    except (ImportError, ValueError, MediaError) as exc:
        return CheckResult(
            "camera", False, f"no H.264 encoder: {exc}", "install gstreamer1.0-plugins-ugly"
        )
    if config.sim.enabled:
        return CheckResult("camera", True, f"--sim test pattern, encoder {encoder}")
    if not os.path.exists(navcam.device):
        return CheckResult(
            "camera",
            False,
            f"{navcam.device} does not exist (encoder {encoder})",
            "plug the camera in, or set navcam.device (v4l2-ctl --list-devices)",
        )
    return CheckResult("camera", True, f"{navcam.device}, encoder {encoder}")


def check_gpio(config: PlatformConfig) -> CheckResult | None:
    outputs = [
        value
        for value in (config.motor.main_lights_output, config.motor.positional_lights_output)
        if value.startswith(GPIO_PREFIX)
    ]
    if not outputs or config.sim.enabled:
        return None
    chips = sorted({GpioLine.parse(value).chip for value in outputs})
    missing = [chip for chip in chips if not os.path.exists(chip)]
    if missing:
        return CheckResult(
            "gpio", False, f"{', '.join(missing)} missing", "check the lights' gpio:CHIP:LINE"
        )
    return CheckResult("gpio", True, f"{', '.join(chips)} present")


# --------------------------------------------------------------------------- files, disk, time


def check_fleet_key(config: PlatformConfig) -> CheckResult | None:
    if config.security.insecure:
        return CheckResult("fleet key", False, "security.insecure: no fleet key", "unset it")
    path = security.key_path(config.security.key_file)
    try:
        security.load_key(path)
    except security.FleetKeyError as exc:
        return CheckResult("fleet key", False, str(exc), f"install the fleet's key at {path}")
    return CheckResult("fleet key", True, f"{path} (owner only)")


def check_signing_key(config: PlatformConfig) -> CheckResult | None:
    if not config.mavlink.enabled or not config.mavlink.signing_key_file:
        return None
    from platformd.mavlink.signing import SigningKeyError, load_signing_key

    path = config.mavlink.signing_key_file
    try:
        load_signing_key(Path(path))
    except SigningKeyError as exc:
        return CheckResult("signing key", False, str(exc), f"chmod 600 {path}")
    return CheckResult("signing key", True, f"{path} (owner only)")


def check_disk(config: PlatformConfig) -> CheckResult | None:
    recorder = config.recorder
    if not recorder.enabled:
        return None
    directory = Path(recorder.dir) if recorder.dir else security.state_dir() / "recordings"
    existing = directory
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    free = shutil.disk_usage(existing).free
    need = recorder.min_free_bytes
    if not os.access(existing, os.W_OK):
        return CheckResult(
            "disk", False, f"{existing} is not writable", f"chown the recorder's dir {directory}"
        )
    if free < need * 2:
        return CheckResult(
            "disk",
            False,
            f"{free / 1e6:.0f} MB free for {directory}; the recorder keeps {need / 1e6:.0f} MB",
            "free space or set recorder.dir to a larger disk",
        )
    return CheckResult("disk", True, f"{free / 1e9:.1f} GB free for {directory}")


def check_clock(config: PlatformConfig) -> CheckResult:
    now = time.time()
    if now < CLOCK_SET_AFTER:
        return CheckResult(
            "clock",
            False,
            f"the clock says {time.strftime('%Y-%m-%d', time.gmtime(now))}: never set",
            "let NTP set it (timedatectl set-ntp true) or fit an RTC",
        )
    synced = Path("/run/systemd/timesync/synchronized").exists()
    return CheckResult(
        "clock",
        True,
        f"{time.strftime('%Y-%m-%d %H:%M:%S', time.gmtime(now))} UTC"
        + (", NTP synchronized" if synced else " (NTP state unknown)"),
    )


def check_last_word(config: PlatformConfig) -> CheckResult:
    """Not a failure either way: what the platform will do at start (platformd.arming)."""
    configured = config.arming.state_file
    path = Path(configured) if configured else security.state_dir() / "last_word.json"
    word = LastWordStore(path).load()
    if word is None:
        return CheckResult("last word", True, "none: nothing starts by itself")
    when = time.strftime("%Y-%m-%d %H:%M:%S", time.gmtime(word.at))
    then = (
        "autostart resumes the patrol (pre-arm, countdown)"
        if word.word == "start" and config.autonomy.autostart
        else "nothing moves until an operator says so"
    )
    return CheckResult("last word", True, f"{word.word} by {word.by} at {when} UTC: {then}")


def _permission_fix(exc: OSError) -> str:
    if isinstance(exc, PermissionError):
        return "add the platform's user to the dialout group (sudo usermod -aG dialout USER)"
    return "check the port and that no other program holds it"
