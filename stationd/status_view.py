"""The operator's status display in a terminal: ``brasidas-station status ID [--watch]``.

:func:`render` is pure (a telemetry report in, lines out); :func:`watch` polls the station
daemon's ``get_telemetry`` over its local WebSocket API and redraws in place with ANSI codes.
"""

from __future__ import annotations

import asyncio
import shutil
import sys
import time
from collections.abc import Callable
from typing import Any, TextIO

from brasidas.codecs.jsonrpc import RpcError
from brasidas.codecs.telemetry_schema import (
    SCHEMA_VERSION,
    Admission,
    Arming,
    Attitude,
    Automation,
    Autonomy,
    Battery,
    Computer,
    Controller,
    Diagnostics,
    Gps,
    Lights,
    Motion,
    Motor,
    Override,
    Platforms,
    Pose,
    RecorderStatus,
    Section,
    Streams,
    Turret,
    VelocityLink,
    snapshot_from_json,
)
from brasidas.config import StationConfig
from brasidas.rpc import RpcClient
from stationd.api_client import CliError

RED = "\x1b[1;37;41m"
YELLOW = "\x1b[33m"
GREEN = "\x1b[32m"
DIM = "\x1b[2m"
RESET = "\x1b[0m"
HOME = "\x1b[H"
CLEAR_LINE = "\x1b[K"
CLEAR_BELOW = "\x1b[J"
CLEAR_SCREEN = "\x1b[2J"
HIDE_CURSOR = "\x1b[?25l"
SHOW_CURSOR = "\x1b[?25h"


def render(report: dict[str, Any], *, color: bool = True, now: float | None = None) -> list[str]:
    """The report (``get_telemetry`` answer) as display lines."""
    if "snapshot" not in report:
        return [f"telemetry  unavailable: {report.get('error', 'no report')}"]
    paint = _painter(color)
    link: dict[str, Any] = report.get("link") or {}
    warnings: list[dict[str, Any]] = report.get("warnings") or []
    clock = time.strftime("%H:%M:%S", time.localtime(now if now is not None else time.time()))
    if report.get("schema") != SCHEMA_VERSION:
        # Another schema's field names would only show as blanks: say why instead.
        return [
            f"{report.get('platform_id', '?')}   {clock}",
            paint(
                f"the station daemon reports telemetry schema v{report.get('schema')}; "
                f"this command reads v{SCHEMA_VERSION} (update the older of the two)",
                RED,
            ),
        ]
    snap = snapshot_from_json(report.get("snapshot") or {})
    override = snap.get(Override) or Override()
    holder = f" by {override.station}" if override.station else ""
    lines = [
        f"{report.get('platform_id', '?')}   {paint(override.mode.upper(), YELLOW)}{holder}   {clock}"
    ]
    if warnings:
        lines.append(
            "WARNINGS   " + "  ".join(paint(f" {w['message'].upper()} ", RED) for w in warnings)
        )
    else:
        lines.append("WARNINGS   " + paint("none", GREEN))
    rows: list[tuple[str, type[Section], Callable[[Any], str]]] = [
        ("lights", Lights, _lights),
        ("battery", Battery, _battery),
        ("controller", Controller, _controller),
        ("motor", Motor, _motor),
        ("gps", Gps, _gps),
        ("attitude", Attitude, _attitude),
        ("computer", Computer, _computer),
        ("velocity", VelocityLink, _velocity),
        ("motion", Motion, _motion),
        ("pose", Pose, _pose),
        ("autonomy", Autonomy, _autonomy),
        ("automation", Automation, _automation),
        ("streams", Streams, _streams),
        ("platforms", Platforms, _platforms),
        ("recorder", RecorderStatus, _recorder),
        ("arming", Arming, _arming),
    ]
    for title, section, show in rows:
        error = snap.error(section)
        value = snap.get(section)
        if error is not None:
            text = paint(f"ERROR {error}", RED)
        elif value is None:
            text = "-"
        else:
            text = show(value)
            if getattr(value, "stale", False):
                text += "  " + paint(f"STALE ({_age(getattr(value, 'age_ms', None))})", RED)
        lines.append(f"{title:<10} {text}")
    turret = snap.get(Turret)
    if turret is not None:  # only on a platform that carries one
        lines.append(f"turret     {_turret(turret)}")
    lines.append(f"link       {_link(link)}")
    admission = snap.get(Admission)
    if admission is not None and (admission.counters or admission.refused):
        lines.append(f"admission  {_admission(admission)}")
    diag = snap.get(Diagnostics)
    if diag is not None:
        restarts = diag.actor_restarts
        failed = {k: v for k, v in diag.section_errors.items() if v}
        lines.append(
            "diagnostic restarts "
            + (", ".join(f"{k} {v}" for k, v in restarts.items()) or "none")
            + f"  bus errors {diag.bus_delivery_errors}"
            + f"  auth failures {_text(diag.auth_failures)}"
            + (f"  section errors {_text(failed)}" if failed else "")
        )
    if link.get("error"):
        lines.append(paint(link["error"], RED))
    return lines


def _admission(admission: Admission) -> str:
    """What signaling refused or closed of strangers: lately, since start, held now."""
    parts = []
    if admission.refused:
        parts.append(
            f"refused {admission.refused} from {admission.refusing} in {admission.window_s:g} s"
        )
    since = ", ".join(f"{name} {value}" for name, value in sorted(admission.counters.items()))
    if since:
        parts.append(f"since start: {since}")
    parts.append(f"strangers now {admission.strangers}")
    return "; ".join(parts)


def frame(lines: list[str], width: int) -> str:
    """One in-place redraw: cursor home, each line cleared to its end, the rest cleared."""
    body = "".join(_clip(line, width) + CLEAR_LINE + "\n" for line in lines)
    return HOME + body + CLEAR_BELOW


async def watch(
    config: StationConfig,
    platform_id: str,
    *,
    interval: float = 0.2,
    frames: int = 0,
    out: TextIO | None = None,
    color: bool | None = None,
) -> int:
    """Redraw the status of ``platform_id`` every ``interval`` s until interrupted (or ``frames``)."""
    out = sys.stdout if out is None else out
    color = out.isatty() if color is None else color
    client = await _open(config)
    out.write(HIDE_CURSOR + CLEAR_SCREEN)
    drawn = 0
    try:
        while not frames or drawn < frames:
            try:
                report = await client.call("get_telemetry", {"platform_id": platform_id})
                lines = render(report, color=color)
            except RpcError as err:
                lines = [f"{platform_id}: {err.message}"]
            width = shutil.get_terminal_size((120, 24)).columns
            out.write(frame([*lines, _painter(color)("Ctrl-C to quit", DIM)], width))
            out.flush()
            drawn += 1
            if frames and drawn >= frames:
                break
            await asyncio.sleep(interval)
    finally:
        out.write(SHOW_CURSOR)
        out.flush()
        await client.close()
    return 0


async def report_once(config: StationConfig, platform_id: str, wait: float = 1.5) -> Any:
    """One ``get_telemetry`` answer, waiting up to ``wait`` s for the first datagrams."""
    client = await _open(config)
    try:
        deadline = time.monotonic() + wait
        while True:
            report = await client.call("get_telemetry", {"platform_id": platform_id})
            if report.get("snapshot") or time.monotonic() > deadline:
                return report
            await asyncio.sleep(0.05)
    finally:
        await client.close()


async def _open(config: StationConfig) -> RpcClient:
    station = config.station
    url = f"http://{station.api_host}:{station.api_port}/api/rpc/ws"
    client = RpcClient(url, timeout=station.connect_timeout * 2 + 2)
    try:
        await client.open()
    except (OSError, TimeoutError):
        raise CliError(
            f"the station daemon is not running at {url} (start it with 'brasidas-station serve')"
        ) from None
    return client


# --------------------------------------------------------------------------- sections


def _painter(color: bool) -> Any:
    def paint(text: str, code: str) -> str:
        return f"{code}{text}{RESET}" if color else text

    return paint


def _num(value: Any, fmt: str = ".1f", unit: str = "") -> str:
    if isinstance(value, int | float) and not isinstance(value, bool):
        return f"{value:{fmt}}{unit}"
    return "-"


def _text(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, dict):
        return "  ".join(f"{k} {_text(v)}" for k, v in value.items())
    return str(value)


def _pair(values: Any, fmt: str, unit: str) -> str:
    if isinstance(values, tuple):
        return "/".join(_num(v, fmt) for v in values) + unit
    return _num(values, fmt, unit)


def _age(age_ms: int | None) -> str:
    return "-" if age_ms is None else f"{age_ms / 1000:.1f} s old"


def _lights(lights: Lights) -> str:
    text = (
        f"main {'ON' if lights.main else 'off'}  positional {'ON' if lights.positional else 'off'}"
    )
    errors = "; ".join(f"{which}: {error}" for which, error in sorted(lights.errors.items()))
    return f"{text}  ({errors})" if errors else text


def _battery(battery: Battery) -> str:
    level = battery.level or ("monitor off" if not battery.monitor else "-")
    return f"{_num(battery.volts, '.1f', ' V')}  {level}"


def _controller(controller: Controller) -> str:
    state = "connected" if controller.connected else "NOT CONNECTED"
    text = (
        f"{state}  heatsink {_pair(controller.temps_c, '.0f', ' °C')}"
        f"  motors {_pair(controller.amps, '.1f', ' A')}"
    )
    return text + (f"  {controller.error}" if controller.error else "")


def _motor(motor: Motor) -> str:
    return (
        f"desired {_pair(motor.desired, 'd', '')}  acknowledged {_pair(motor.acknowledged, 'd', '')}"
        + (f"  {motor.error}" if motor.error else "")
    )


def _gps(gps: Gps) -> str:
    if not gps.fix:
        lost = f" ({gps.lost_for_s:.0f} s)" if gps.lost_for_s else ""
        last = (
            f"  last {_num(gps.lat, '.6f')}, {_num(gps.lon, '.6f')}" if gps.lat is not None else ""
        )
        return "NO FIX" + lost + last
    parts = [f"{_num(gps.lat, '.6f')}, {_num(gps.lon, '.6f')}"]
    if gps.alt is not None:
        parts.append(f"alt {_num(gps.alt, '.0f', ' m')}")
    if gps.sats is not None:
        parts.append(f"{gps.sats} sats")
    if gps.hdop is not None:
        parts.append(f"hdop {_num(gps.hdop)}")
    if gps.speed is not None:
        parts.append(_num(gps.speed, ".1f", " m/s"))
    if gps.course is not None:
        parts.append(f"course {_num(gps.course, '.0f', '°')}")
    return "  ".join(parts)


def _attitude(attitude: Attitude) -> str:
    parts = [
        f"{name} {_num(value, '.1f', '°')}"
        for name, value in (
            ("roll", attitude.roll),
            ("pitch", attitude.pitch),
            ("yaw", attitude.yaw),
        )
    ]
    imu = attitude.imu
    if imu is not None:
        if imu.temp_c is not None:
            parts.append(f"imu {_num(imu.temp_c, '.1f', ' °C')}")
        if imu.error:
            parts.append(f"IMU ERROR {imu.error}")
    return "  ".join(parts)


def _computer(computer: Computer) -> str:
    load = " ".join(_num(v, ".2f") for v in computer.load) if computer.load else "-"
    return (
        f"cpu {_num(computer.cpu_temp_c, '.1f', ' °C')}  load {load}"
        f"  mem free {_num(computer.mem_free_mb, '.0f', ' MB')}"
    )


def _velocity(velocity: VelocityLink) -> str:
    dropped = {k: v for k, v in velocity.dropped.items() if v}
    reasons = f" ({', '.join(f'{k} {v}' for k, v in dropped.items())})" if dropped else ""
    age = (
        f"  age {velocity.age_ms:.0f} ms (max {velocity.age_max_ms:.0f})"
        if velocity.age_ms is not None and velocity.age_max_ms is not None
        else ""
    )
    return f"accepted {velocity.accepted}  dropped {sum(dropped.values())}{reasons}{age}"


def _motion(motion: Motion) -> str:
    deadman = "  DEADMAN" if motion.deadman else ""
    return f"{motion.mode}  linear {motion.linear:+.2f}  angular {motion.angular:+.2f}{deadman}"


def _pose(pose: Pose) -> str:
    where = (
        f"{pose.lat:.6f},{pose.lon:.6f}" if pose.lat is not None and pose.lon is not None else "?"
    )
    heading = f"{pose.heading:.0f}°" if pose.heading is not None else "heading unknown"
    sigma = f" ±{pose.sigma_m:.1f} m" if pose.sigma_m is not None else ""
    return f"{where}{sigma}  {heading}  {pose.speed:.1f} m/s  ({pose.source})"


def _autonomy(patrol: Autonomy) -> str:
    """Holding stands out: it is what the operator must act on."""
    if patrol.waypoint is None:
        text = patrol.state
    else:
        distance = f" {patrol.distance_m:.0f} m" if patrol.distance_m is not None else ""
        text = f"{patrol.state}  waypoint {patrol.waypoint + 1}/{patrol.waypoints}{distance}  lap {patrol.lap}"  # from 1
    if patrol.reason:
        text += f"  ({patrol.reason})"
    if patrol.state == "holding":
        text = "HOLDING" + text.removeprefix("holding")
    return text if patrol.enabled else text + "  [switched off]"


def _automation(automation: Automation) -> str:
    return (
        "  ".join(f"{name} {'on' if on else 'OFF'}" for name, on in automation.switches.items())
        or "-"
    )


def _turret(turret: Turret) -> str:
    if not turret.connected:
        text = f"line down: {turret.error}" if turret.error else "line down"
    else:
        text = (
            f"trigger {'ARMED' if turret.trigger else 'safe'}  "
            f"az {_num(turret.azimuth, '.1f', '°')}  el {_num(turret.elevation, '.1f', '°')}"
        )
    streams = "  ".join(f"{name} {state}" for name, state in turret.streams.items())
    return f"{text}  sight {streams}" if streams else text


def _streams(streams: Streams) -> str:
    if not streams.states:
        return "-"
    return "  ".join(f"{name} {state}" for name, state in streams.states.items())


def _link(link: dict[str, Any]) -> str:
    if not link:
        return "-"
    rejected = {k: v for k, v in (link.get("rejected") or {}).items() if v}
    reasons = f" ({', '.join(f'{k} {v}' for k, v in rejected.items())})" if rejected else ""
    return (
        f"received {link.get('received', 0)}  loss {_num(link.get('loss_pct'), '.1f', '%')}"
        f"  silence {_num(link.get('silence_s'), '.1f', ' s')}"
        f"  rtt {_num(link.get('round_trip_ms'), '.1f', ' ms')}"
        f"  rejected {link.get('rejected_total', 0)}{reasons}"
    )


def _platforms(platforms: Platforms) -> str:
    heard = [f"{name} ({age:.0f} s ago)" for name, age in platforms.age_s.items()]
    # The platform's own mesh: other platforms' beacons (its station link is the "link" row).
    return "  ".join(heard) or "no other platform's beacon heard"


def _recorder(recorder: RecorderStatus) -> str:
    state = (
        "recording"
        if recorder.recording
        else f"STOPPED: {recorder.reason}"
        if recorder.reason
        else "not recording yet"
    )
    return f"{state}  dropped {recorder.dropped}  not recorded {recorder.not_recorded}"


def _clip(line: str, width: int) -> str:
    """Cut to ``width`` visible characters, leaving ANSI codes whole."""
    visible = 0
    out = []
    i = 0
    while i < len(line):
        if line[i] == "\x1b":
            end = line.find("m", i)
            if end == -1:
                break
            out.append(line[i : end + 1])
            i = end + 1
            continue
        if visible >= width:
            i += 1
            continue
        out.append(line[i])
        visible += 1
        i += 1
    return "".join(out)


def _arming(arming: Arming) -> str:
    """ARMED or disarmed, the autostart countdown, every failing pre-arm check, the last stop."""
    parts = ["ARMED" if arming.armed else "disarmed"]
    if arming.countdown_s is not None:
        parts.append(f"AUTOSTART: arming and patrolling in {arming.countdown_s:.0f} s")
    parts.append("pre-arm ok" if arming.ready else "; ".join(arming.prearm))
    if arming.last_stop:
        parts.append(f"last stop: {arming.last_stop}")
    return "  ".join(parts)
