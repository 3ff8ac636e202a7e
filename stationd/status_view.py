"""The operator's status display in a terminal: ``brasidas-station status ID [--watch]``.

:func:`render` is pure (a telemetry report in, lines out); :func:`watch` polls the station
daemon's ``get_telemetry`` over its local WebSocket API and redraws in place with ANSI codes.
"""

from __future__ import annotations

import asyncio
import shutil
import sys
import time
from typing import Any, TextIO

from brasidas.codecs.jsonrpc import RpcError
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
    snap: dict[str, Any] = report.get("snapshot") or {}
    link: dict[str, Any] = report.get("link") or {}
    warnings: list[dict[str, Any]] = report.get("warnings") or []
    clock = time.strftime("%H:%M:%S", time.localtime(now if now is not None else time.time()))
    mode = str(snap.get("mode", "?")).upper()
    override = snap.get("override") or {}
    holder = f" by {override['station']}" if override.get("station") else ""
    lines = [f"{report.get('platform_id', '?')}   {paint(mode, YELLOW)}{holder}   {clock}"]
    if warnings:
        lines.append(
            "WARNINGS   " + "  ".join(paint(f" {w['message'].upper()} ", RED) for w in warnings)
        )
    else:
        lines.append("WARNINGS   " + paint("none", GREEN))
    lines += [
        f"lights     {_lights(snap.get('lights'))}",
        f"battery    {_battery(snap.get('battery'))}",
        f"controller {_controller(snap.get('controller'))}",
        f"gps        {_gps(snap.get('gps'))}",
        f"attitude   {_attitude(snap.get('attitude'))}",
        f"computer   {_computer(snap.get('computer'))}",
        f"link       {_link(link)}",
        f"velocity   {_velocity(snap.get('velocity_link') or (snap.get('link') or {}).get('velocity'))}",
        f"streams    {_streams(snap.get('streams'))}",
        f"autonomy   {_text(snap.get('autonomy'))}",
    ]
    if snap.get("diagnostics"):
        diag = snap["diagnostics"]
        restarts = diag.get("actor_restarts") or {}
        lines.append(
            "diagnostic restarts "
            + (", ".join(f"{k} {v}" for k, v in restarts.items()) or "none")
            + f"  bus errors {diag.get('bus_delivery_errors', '-')}"
            + f"  auth failures {diag.get('auth_failures', '-')}"
        )
    if link.get("error"):
        lines.append(paint(link["error"], RED))
    return lines


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


def _get(section: dict[str, Any], *names: str) -> Any:
    for name in names:
        if section.get(name) is not None:
            return section[name]
    return None


def _text(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, dict):
        return "  ".join(f"{k} {_text(v)}" for k, v in value.items())
    return str(value)


def _pair(values: Any, fmt: str, unit: str) -> str:
    if isinstance(values, list):
        return "/".join(_num(v, fmt) for v in values) + unit
    return _num(values, fmt, unit)


def _lights(lights: Any) -> str:
    if not isinstance(lights, dict):
        return "-"
    return (
        f"main {'ON' if lights.get('main') else 'off'}  "
        f"positional {'ON' if lights.get('positional') else 'off'}"
    )


def _battery(battery: Any) -> str:
    if not isinstance(battery, dict):
        return "-"
    level = battery.get("level") or ("monitor off" if battery.get("monitor") is False else "-")
    return f"{_num(battery.get('volts'), '.1f', ' V')}  {level}"


def _controller(controller: Any) -> str:
    if not isinstance(controller, dict):
        return "-"
    state = "connected" if controller.get("connected") else "NOT CONNECTED"
    return (
        f"{state}  heatsink {_pair(controller.get('temps_c'), '.0f', ' °C')}"
        f"  motors {_pair(controller.get('amps'), '.1f', ' A')}"
    )


def _gps(gps: Any) -> str:
    if not isinstance(gps, dict):
        return "-"
    if not gps.get("fix"):
        return "NO FIX" + (f" ({gps['lost_for_s']:.0f} s)" if gps.get("lost_for_s") else "")
    lat = _get(gps, "latitude", "lat")
    lon = _get(gps, "longitude", "lon")
    parts = [f"{_num(lat, '.6f')}, {_num(lon, '.6f')}"]
    alt = _get(gps, "altitude", "altitude_m", "alt")
    if alt is not None:
        parts.append(f"alt {_num(alt, '.0f', ' m')}")
    sats = _get(gps, "satellites", "sats", "num_sats")
    if sats is not None:
        parts.append(f"{sats} sats")
    hdop = _get(gps, "hdop")
    if hdop is not None:
        parts.append(f"hdop {_num(hdop)}")
    speed = _get(gps, "speed_mps", "speed_ms", "speed")
    if speed is not None:
        parts.append(f"{_num(speed, '.1f', ' m/s')}")
    course = _get(gps, "course", "course_deg", "track")
    if course is not None:
        parts.append(f"course {_num(course, '.0f', '°')}")
    return "  ".join(parts)


def _attitude(attitude: Any) -> str:
    if not isinstance(attitude, dict):
        return "-"
    parts = []
    for name in ("roll", "pitch", "yaw"):
        value = _get(attitude, name, f"{name}_deg")
        parts.append(f"{name} {_num(value, '.1f', '°')}")
    imu = attitude.get("imu")
    if isinstance(imu, dict):
        temp = _get(imu, "temperature_c", "temp_c", "temperature")
        if temp is not None:
            parts.append(f"imu {_num(temp, '.1f', ' °C')}")
        error = _get(imu, "error")
        if error:
            parts.append(f"IMU ERROR {error}")
    return "  ".join(parts)


def _computer(computer: Any) -> str:
    if not isinstance(computer, dict):
        return "-"
    load = computer.get("load")
    load_text = " ".join(_num(v, ".2f") for v in load) if isinstance(load, list) else "-"
    return (
        f"cpu {_num(computer.get('cpu_temp_c'), '.1f', ' °C')}  load {load_text}"
        f"  mem free {_num(computer.get('mem_free_mb'), '.0f', ' MB')}"
    )


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


def _velocity(velocity: Any) -> str:
    if not isinstance(velocity, dict):
        return "-"
    dropped = {k: v for k, v in (velocity.get("dropped") or {}).items() if v}
    total = sum(v for v in dropped.values() if isinstance(v, int))
    reasons = f" ({', '.join(f'{k} {v}' for k, v in dropped.items())})" if dropped else ""
    return f"accepted {velocity.get('accepted', 0)}  dropped {total}{reasons}"


def _streams(streams: Any) -> str:
    if not isinstance(streams, dict) or not streams:
        return "-"
    return "  ".join(f"{name} {_text(state)}" for name, state in streams.items())


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
