"""``brasidas-station``: the station daemon and the operator's commands.

``serve`` runs the daemon (discovery, platform sessions, the local API). ``list`` listens for
beacons itself. The other commands ask the running daemon through its local API, so sessions
(and the manual override they hold) outlive a single command.
"""

from __future__ import annotations

import argparse
import asyncio
import datetime
import json
import logging
import re
import sys
import textwrap
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from brasidas import security
from brasidas.actor import stop_on_signals
from brasidas.codecs.jsonrpc import CONTROL_REFUSED, TIMEOUT, RpcError
from brasidas.codecs.telemetry_schema import Override, snapshot_from_json
from brasidas.config import ConfigError, StationConfig, load_config
from brasidas.log import LEVELS, level_argument, setup_logging
from stationd.api_client import CliError, api_call_async

_LOGGER = logging.getLogger("stationd")


# ---------------------------------------------------------------------------- local API client


def api_call(config: StationConfig, method: str, **params: Any) -> Any:
    return asyncio.run(api_call_async(config, method, **params))


# ---------------------------------------------------------------------------- commands


def _print(args: argparse.Namespace, value: Any, human: Callable[[Any], str]) -> None:
    print(
        json.dumps(value, indent=2, sort_keys=True, allow_nan=False) if args.json else human(value)
    )


def _ack(answer: dict[str, Any]) -> str:
    if answer.get("accepted"):
        extra = (
            f" {json.dumps(answer['result'], allow_nan=False)}"
            if answer.get("result") is not None
            else ""
        )
        return f"acknowledged{extra}"
    return f"rejected: {answer.get('reason') or 'no reason given'}"


def _check_ack(answer: Any) -> int:
    return 0 if isinstance(answer, dict) and answer.get("accepted") else 1


def describe_connection(summary: dict[str, Any]) -> str:
    """What `connect` prints: the platform, its limits, velocity, telemetry and streams."""
    params = summary.get("parameters", {})
    caps = summary.get("capabilities", {})
    lines = [
        f"platform   {summary['platform_id']} ({params.get('model', '?')}, "
        f"software {params.get('software_version', '?')}"
        f"{', simulated' if params.get('simulated') else ''})",
        f"signaling  {summary['signaling_url']}  session {summary['session'][:8]}…",
        f"limits     {json.dumps(params.get('limits', {}), allow_nan=False)}",
        f"velocity   {json.dumps(caps.get('velocity', {}), allow_nan=False)}",
        f"telemetry  {json.dumps(caps.get('telemetry', {}), allow_nan=False)}",
        "streams    "
        + (
            ", ".join(
                f"{s.get('name')} ({s.get('kind')}"
                + (
                    f" {s.get('width')}x{s.get('height')}@{s.get('framerate')}"
                    if s.get("width")
                    else ""
                )
                + ")"
                for s in caps.get("streams", [])
            )
            or "none"
        ),
        "payload    "
        + (
            ", ".join(
                f"{p.get('name')} (groups {', '.join(map(str, p.get('groups', [])))}"
                + (f"; streams {', '.join(p['streams'])}" if p.get("streams") else "")
                + ")"
                for p in caps.get("payloads", [])
            )
            or "none"
        ),
        f"override   {'ENGAGED' if summary.get('manual_override') else 'disengaged'}",
    ]
    return "\n".join(lines)


def cmd_connect(args: argparse.Namespace, config: StationConfig) -> int:
    summary = api_call(config, "connect", platform_id=args.id, url=args.url or "")
    _print(args, summary, describe_connection)
    return 0


def cmd_disconnect(args: argparse.Namespace, config: StationConfig) -> int:
    closed = api_call(config, "disconnect", platform_id=args.id)
    _print(args, closed, lambda c: "disconnected" if c else f"not connected to {args.id}")
    return 0


def cmd_status(args: argparse.Namespace, config: StationConfig) -> int:
    from stationd import status_view

    if args.watch:
        return asyncio.run(
            status_view.watch(config, args.id, interval=args.interval, frames=args.frames)
        )
    summary = api_call(config, "status", platform_id=args.id)
    try:
        summary["telemetry"] = asyncio.run(status_view.report_once(config, args.id))
    except RpcError as err:
        summary["telemetry"] = {"error": err.message}

    def human(s: dict[str, Any]) -> str:
        override = snapshot_from_json(s.get("report", {})).get(Override)
        rtt = s.get("round_trip_ms")
        return "\n".join(
            [
                describe_connection(s),
                f"mode       {override.mode if override is not None else '?'}",
                f"round trip {rtt:.2f} ms" if rtt is not None else "round trip -",
                "",
                *status_view.render(s["telemetry"], color=sys.stdout.isatty()),
            ]
        )

    _print(args, summary, human)
    return 0


def _rpc_error_text(err: RpcError) -> str:
    """An error answer as the operator reads it: a refusal of control is not a timeout."""
    if err.code == CONTROL_REFUSED:
        return f"control refused: {err.message} ('movrd ID on --force' takes control)"
    if err.code == TIMEOUT:
        return f"timed out: {err.message}"
    return err.message


def cmd_movrd(args: argparse.Namespace, config: StationConfig) -> int:
    answer = api_call(
        config, "movrd", platform_id=args.id, engaged=args.state == "on", force=args.force
    )
    _print(args, answer, _ack)
    return _check_ack(answer)


def _describe_arming(answer: dict[str, Any]) -> str:
    lines = [
        f"{'ARMED' if answer.get('armed') else 'disarmed'}"
        f" · pre-arm {'ok' if answer.get('ready') else 'failing'}"
    ]
    lines += [f"  {reason}" for reason in answer.get("prearm") or []]
    if answer.get("countdown_s") is not None:
        lines.append(f"autostart in {answer['countdown_s']:.0f} s")
    if answer.get("last_stop"):
        lines.append(f"last stop: {answer['last_stop']}")
    return "\n".join(lines)


def cmd_arming(args: argparse.Namespace, config: StationConfig) -> int:
    """``arm``, ``disarm [--force]``, ``stop``: the platform's answer, or its refusal."""
    params: dict[str, Any] = {"force": True} if getattr(args, "force", False) else {}
    answer = api_call(config, args.command, platform_id=args.id, **params)
    _print(args, answer, _describe_arming)
    return 0


def cmd_cmd(args: argparse.Namespace, config: StationConfig) -> int:
    answer = api_call(
        config,
        "command",
        platform_id=args.id,
        group=args.group,
        command=args.command_id,
        payload=args.payload,
    )
    _print(args, answer, _ack)
    return _check_ack(answer)


def cmd_lights(args: argparse.Namespace, config: StationConfig) -> int:
    answer = api_call(
        config, "lights", platform_id=args.id, which=args.which, on=args.state == "on"
    )
    _print(args, answer, _ack)
    return _check_ack(answer)


def cmd_drive(args: argparse.Namespace, config: StationConfig) -> int:
    from stationd.drive import run_drive

    return run_drive(args, config)


def cmd_view(args: argparse.Namespace, config: StationConfig) -> int:
    from stationd.view import run_view

    return run_view(args, config)


STREAM_ACTIONS = {"start": "stream_start", "pause": "stream_pause", "stop": "stream_stop"}


def _describe_stream(stream: dict[str, Any]) -> str:
    where = f" -> {stream['destination']}" if stream.get("destination") else ""
    why = f" ({stream['reason']})" if stream.get("reason") else ""
    return f"{stream.get('name', '?'):<16} {stream.get('kind', ''):<15} {stream.get('state')}{where}{why}"


def cmd_stream(args: argparse.Namespace, config: StationConfig) -> int:
    if args.name is None:
        streams = api_call(config, "streams", platform_id=args.id)
        _print(args, streams, lambda v: "\n".join(map(_describe_stream, v)) or "no streams")
        return 0
    if args.action is None:
        raise CliError("say what to do with the stream: start, pause or stop")
    params: dict[str, Any] = {"platform_id": args.id, "stream": args.name}
    if args.action == "start":
        params.update(host=args.host or "", port=args.port or 0)
    answer = api_call(config, STREAM_ACTIONS[args.action], **params)
    _print(args, answer, _describe_stream)
    return 1 if answer.get("state") == "failed" else 0


def _describe_patrol(patrol: dict[str, Any]) -> str:
    waypoint = patrol.get("waypoint")
    distance = patrol.get("distance_m")
    lines = [
        f"state      {patrol.get('state')}"
        + ("" if patrol.get("enabled", True) else " (switched off)"),
        # Counted from 1, as the console and the platform's refusals count them.
        f"waypoint   {'-' if waypoint is None else waypoint + 1} of {patrol.get('waypoints', 0)}",
        f"distance_m {'-' if distance is None else distance}",
        f"lap        {patrol.get('lap', 0)}",
        f"reason     {patrol.get('reason') or '-'}",
    ]
    return "\n".join(lines)


def _read_file(name: str) -> str:
    """A map or route file's text (UTF-8, bounded), for the station to read."""
    from brasidas.mapfiles import MAX_FILE_BYTES

    try:
        with Path(name).open("rb") as file:
            data = file.read(MAX_FILE_BYTES + 1)
    except OSError as err:
        raise CliError(f"cannot read {name}: {err}") from None
    if len(data) > MAX_FILE_BYTES:
        size = Path(name).stat().st_size if Path(name).is_file() else len(data)
        raise CliError(
            f"{name}: {size} bytes, over the limit of {MAX_FILE_BYTES} bytes for a map or "
            "route file (docs/operator-guide.md: Limits)"
        )
    if data.startswith(b"PK\x03\x04"):
        raise CliError(f"{name}: a zip archive (a KMZ?): unzip it and give the .kml inside")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise CliError(f"{name}: not UTF-8 text ({err})") from None


def _notes(value: dict[str, Any]) -> str:
    """What the station assumed or left aside reading a file, one line each."""
    return "".join(f"\n  note: {note}" for note in value.get("notes", []))


def cmd_map(args: argparse.Namespace, config: StationConfig) -> int:
    text = _read_file(args.file)
    answer = api_call(
        config,
        "map_import",
        platform_id=args.id,
        text=text,
        filename=Path(args.file).name,
        boundary=args.boundary or "",
        keepouts=args.keepouts or "",
        boundary_bbox=args.boundary_bbox,
        union=args.union,
    )

    def human(value: dict[str, Any]) -> str:
        area = value["map"]
        return (
            f"map {area['name']!r} loaded ({value.get('format', '?')}): "
            f"{area['area_m2']:.0f} m², "
            f"{len(area['keepouts'])} keep-out zones, {len(area['points'])} named points; "
            "waypoints cleared, patrol stopped"
            + _notes(value)
            + "".join(f"\n  note: {note}" for note in area.get("notes", []))  # ids made unique
        )

    _print(args, answer, human)
    return 0


EXPORT_SUFFIXES = {".plan": "plan", ".waypoints": "waypoints", ".txt": "waypoints"}


def cmd_route(args: argparse.Namespace, config: StationConfig) -> int:
    if args.export:
        return _export_route(args, config)
    items: list[Any] = [waypoint.strip() for waypoint in args.waypoints]
    if not items:
        raise CliError("give a route file, waypoints (LAT,LON or point names) or --export FILE")
    if len(items) == 1 and Path(items[0]).is_file():
        answer = api_call(
            config,
            "route_import",
            platform_id=args.id,
            text=_read_file(items[0]),
            filename=Path(items[0]).name,
            fence=args.fence,
            skip_unsupported=args.skip_unsupported,
        )
    elif args.fence:
        raise CliError("--fence reads a QGC .plan file's geofence: give one file")
    else:
        answer = api_call(config, "route_set", platform_id=args.id, waypoints=items)

    def human(value: dict[str, Any]) -> str:
        kind = "closed, loops" if value["closed"] else "open, driven back in reverse"
        laps = value.get("laps")
        if laps:
            kind = (
                f"closed, {laps} laps, then stops" if value["closed"] else "driven once, then stops"
            )
        fmt = f" from {value['format']}" if value.get("format") else ""
        added = value.get("keepouts_added") or []
        return (
            f"{len(value['waypoints'])} waypoints set{fmt} ({kind})"
            + (f"; keep-outs added: {', '.join(added)}" if added else "")
            + _notes(value)
            + "\n"
            + _describe_patrol(value["patrol"])
        )

    _print(args, answer, human)
    return 0


def _export_route(args: argparse.Namespace, config: StationConfig) -> int:
    if args.waypoints or args.fence:
        raise CliError("--export writes the platform's route: give no waypoints or --fence")
    target = Path(args.export)
    fmt = EXPORT_SUFFIXES.get(target.suffix.lower())
    if fmt is None:
        raise CliError(f"{target}: export to FILE.plan or FILE.waypoints")
    answer = api_call(config, "route_export", platform_id=args.id, format=fmt)
    try:
        target.write_text(answer["text"], encoding="utf-8")
    except OSError as err:
        raise CliError(f"cannot write {target}: {err}") from None
    _print(
        args,
        {"file": str(target), "format": fmt, "waypoints": answer["waypoints"]},
        lambda v: f"{v['waypoints']} waypoints written to {v['file']} ({v['format']})",
    )
    return 0


PATROL_ACTIONS = {None: "patrol_get", "start": "patrol_start", "stop": "patrol_stop"}


def cmd_patrol(args: argparse.Namespace, config: StationConfig) -> int:
    answer = api_call(config, PATROL_ACTIONS[args.action], platform_id=args.id)
    _print(args, answer, _describe_patrol)
    return 0


def cmd_goto(args: argparse.Namespace, config: StationConfig) -> int:
    """``goto ID LAT,LON``: drive there through the platform's planner and stop."""
    try:
        latitude, longitude = (float(part) for part in args.point.strip().split(","))
    except ValueError:
        raise CliError(f"{args.point.strip()!r}: give the point as LAT,LON") from None
    answer = api_call(config, "goto", platform_id=args.id, latitude=latitude, longitude=longitude)
    _print(
        args, answer, lambda v: f"going to {latitude:.7f}, {longitude:.7f}\n" + _describe_patrol(v)
    )
    return 0


def cmd_audio(args: argparse.Namespace, config: StationConfig) -> int:
    from stationd.intercom import run_audio

    return run_audio(args, config)


def cmd_logs(args: argparse.Namespace, config: StationConfig) -> int:
    """``logs ID``: the platform's recordings; ``logs ID get NAME [-o FILE]``: download one."""
    if args.action is None:
        answer = api_call(config, "recordings_list", platform_id=args.id)
        _print(args, answer, _describe_recordings)
        return 0
    if not args.name:
        raise CliError("logs ID get NAME: which recording (see 'brasidas-station logs ID')")
    source = api_call(config, "recording_source", platform_id=args.id, name=args.name)
    target = Path(args.output or Path(args.name).name)
    have = target.stat().st_size if target.exists() else 0
    from stationd.recordings import DownloadError, download

    try:
        size = asyncio.run(download(source["url"], dict(source["headers"]), target, have))
    except DownloadError as err:
        raise CliError(str(err)) from None
    print(f"{target}: {size} bytes")
    return 0


def _describe_recordings(answer: dict[str, Any]) -> str:
    state = "recording" if answer.get("recording") else f"NOT recording: {answer.get('reason')}"
    counters = answer.get("counters", {})
    lines = [f"recorder   {state}; dropped {counters.get('dropped', 0)}"]
    for item in answer.get("recordings", []):
        start = item.get("start")
        when = (
            datetime.datetime.fromtimestamp(start, datetime.UTC).strftime("%Y-%m-%d %H:%M:%S")
            if isinstance(start, int | float)
            else "(being written)"
            if item.get("recording")
            else "?"
        )
        duration = item.get("duration_s")
        length = f"{duration:7.1f} s" if isinstance(duration, int | float) else "      -  "
        channels = sorted(item.get("channels", {}))
        lines.append(
            f"{item['name']}  {when}  {length}  {item['size'] / 1e6:8.2f} MB"
            f"  {len(channels)} channels"
        )
        # The channel names wrapped under the file (32 of them used to make one line).
        lines.extend(
            textwrap.wrap(", ".join(channels), 96, initial_indent="    ", subsequent_indent="    ")
        )
    return "\n".join(lines)


def cmd_keygen(args: argparse.Namespace, config: StationConfig) -> int:
    path = Path(args.path) if args.path else security.key_path(config.security.key_file)
    try:
        security.generate_key(path, overwrite=args.force)
    except FileExistsError:
        raise CliError(
            f"{path} exists; pass --force to replace it (every host needs the new one)"
        ) from None
    _print(args, {"path": str(path)}, lambda v: f"fleet key written to {v['path']}")
    return 0


def cmd_list(args: argparse.Namespace, config: StationConfig) -> int:
    from stationd.discovery import discover

    platforms = asyncio.run(discover(config, station_fleet_key(config), args.wait))

    def human(entries: list[dict[str, Any]]) -> str:
        if not entries:
            return f"no platforms heard in {args.wait:.1f} s"
        return "\n".join(_describe_discovered(entry) for entry in entries)

    _print(args, platforms, human)
    return 0


def _describe_discovered(entry: dict[str, Any]) -> str:
    status = entry.get("status", {})
    flags = [name for name, on in status.items() if on is True]
    position = entry.get("position")
    where = f" at {position[0]:.6f},{position[1]:.6f}" if position else ""
    return f"{entry['id']:<16} {entry['url']:<28} {' '.join(flags) or '-'}{where}"


def cmd_serve(args: argparse.Namespace, config: StationConfig) -> int:
    from stationd.daemon import ConsoleMissing, StationDaemon, load_subsystems

    fleet_key = station_fleet_key(config)
    load_subsystems(config)  # before the loop runs: an import there blocks it

    async def run() -> None:
        await StationDaemon(config, fleet_key).run(stop_on_signals())

    try:
        asyncio.run(run())
    except ConsoleMissing as err:
        raise CliError(f"{err} (reinstall the package)") from None
    return 0


def station_fleet_key(config: StationConfig) -> bytes | None:
    if config.security.insecure:
        return None
    return security.load_key(security.key_path(config.security.key_file))


# ---------------------------------------------------------------------------- parser


COMMANDS: dict[str, Callable[[argparse.Namespace, StationConfig], int]] = {
    "serve": cmd_serve,
    "list": cmd_list,
    "connect": cmd_connect,
    "disconnect": cmd_disconnect,
    "status": cmd_status,
    "movrd": cmd_movrd,
    "cmd": cmd_cmd,
    "lights": cmd_lights,
    "keygen": cmd_keygen,
    "drive": cmd_drive,
    "view": cmd_view,
    "audio": cmd_audio,
    "stream": cmd_stream,
    "map": cmd_map,
    "route": cmd_route,
    "patrol": cmd_patrol,
    "goto": cmd_goto,
    "arm": cmd_arming,
    "disarm": cmd_arming,
    "stop": cmd_arming,
    "logs": cmd_logs,
}


def _common_options(*, top_level: bool) -> argparse.ArgumentParser:
    """Options every command takes, before or after its name.

    The top level holds the defaults; a subcommand's copy leaves absent options out
    (``SUPPRESS``) so it never overwrites what was given before the command name, and its
    ``--set`` items are kept apart and applied after the top level's.
    """
    common = argparse.ArgumentParser(add_help=False)
    default: dict[str, Any] = {} if top_level else {"default": argparse.SUPPRESS}
    common.add_argument("--config", metavar="FILE", help="TOML configuration file", **default)
    common.add_argument(
        "--set",
        dest="overrides" if top_level else "command_overrides",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override a configuration key (repeatable)",
    )
    common.add_argument("--json", action="store_true", help="machine-readable output", **default)
    common.add_argument(
        "--insecure", action="store_true", help="no fleet key (never in the field)", **default
    )
    common.add_argument(
        "-v", "--verbose", action="count", **({"default": 0} if top_level else default)
    )
    common.add_argument(
        "--log-level", type=level_argument, help=", ".join(LEVELS), metavar="LEVEL", **default
    )
    return common


def build_parser() -> argparse.ArgumentParser:
    common = _common_options(top_level=False)
    parser = argparse.ArgumentParser(
        prog="brasidas-station",
        description="Brasidas control station.",
        parents=[_common_options(top_level=True)],
    )
    sub = parser.add_subparsers(dest="command", required=True)
    sub.add_parser("serve", parents=[common], help="run the station daemon")
    p = sub.add_parser("list", parents=[common], help="platforms online (listens for beacons)")
    p.add_argument("--wait", type=float, default=3.5, help="seconds to listen (default 3.5)")
    p = sub.add_parser(
        "connect", parents=[common], help="connect; print parameters and capabilities"
    )
    p.add_argument("id")
    p.add_argument("--url", help="signaling URL, when the platform is not discovered")
    p = sub.add_parser("disconnect", parents=[common], help="end the session")
    p.add_argument("id")
    p = sub.add_parser("status", parents=[common], help="platform status and telemetry")
    p.add_argument("id")
    p.add_argument("--watch", action="store_true", help="live view, refreshed in place")
    p.add_argument("--interval", type=float, default=0.2, help="seconds between refreshes")
    p.add_argument("--frames", type=int, default=0, help=argparse.SUPPRESS)
    p = sub.add_parser("movrd", parents=[common], help="engage or release the manual override")
    p.add_argument("id")
    p.add_argument("state", choices=["on", "off"])
    p.add_argument(
        "--force",
        action="store_true",
        help="take control from the station holding it (it is told at once)",
    )
    p = sub.add_parser("stop", parents=[common], help="stop the platform now (anyone may)")
    p.add_argument("id")
    p = sub.add_parser("arm", parents=[common], help="arm through the pre-arm checks (control)")
    p.add_argument("id")
    p = sub.add_parser("disarm", parents=[common], help="disarm: motors held at zero (anyone)")
    p.add_argument("id")
    p.add_argument("--force", action="store_true", help="a forced disarm, recorded as such")
    p = sub.add_parser("cmd", parents=[common], help="issue a system command (table 10.1)")
    p.add_argument("id")
    p.add_argument("group", type=int)
    p.add_argument("command_id", metavar="command", type=int)
    p.add_argument("payload", nargs="?", default="")
    p = sub.add_parser("lights", parents=[common], help="main or positional lights")
    p.add_argument("id")
    p.add_argument("which", choices=["main", "pos"])
    p.add_argument("state", choices=["on", "off"])
    p = sub.add_parser(
        "drive", parents=[common], help="drive a platform from the keyboard (takes the terminal)"
    )
    p.add_argument("id")
    p.add_argument("--url", help="signaling URL, when the platform is not discovered")
    p.add_argument("--step", type=float, default=0.1, help="command change per key press")
    p = sub.add_parser(
        "view", parents=[common], help="a platform's video in a window, with its latency"
    )
    p.add_argument("id")
    p.add_argument("stream", nargs="?", default="navcam")
    p.add_argument("--url", help="signaling URL, when the platform is not discovered")
    p.add_argument("--port", type=int, default=0, help="UDP port to receive on (default: free)")
    p.add_argument("--sink", default="autovideosink", help="GStreamer sink (fakesink: no window)")
    p.add_argument("--seconds", type=float, default=0, help="stop after this long")
    p.add_argument("--sdp", metavar="FILE", help="write an SDP file for ffplay/VLC instead")
    p = sub.add_parser(
        "stream",
        parents=[common],
        help="a platform's streams; start, pause or stop one (10.1-10.3 act on all)",
    )
    p.add_argument("id")
    p.add_argument("name", nargs="?", help="stream name (navcam, audio_out, ...); none: list")
    p.add_argument("action", nargs="?", choices=sorted(STREAM_ACTIONS))
    p.add_argument("--host", help="start: where to send it (default: this station)")
    p.add_argument("--port", type=int, default=0, help="start: UDP port (default: configured)")
    p = sub.add_parser(
        "audio", parents=[common], help="hear a platform's microphone; --talk to answer"
    )
    p.add_argument("id")
    p.add_argument("--url", help="signaling URL, when the platform is not discovered")
    p.add_argument("--talk", action="store_true", help="send this station's microphone too")
    p.add_argument("--test-tone", action="store_true", help="with --talk: a 440 Hz tone instead")
    p.add_argument(
        "--sink", choices=["auto", "fakesink"], default="auto", help="fakesink: do not play"
    )
    p.add_argument("--seconds", type=float, default=0, help="stop after this long")
    p = sub.add_parser(
        "map",
        parents=[common],
        help="load an area map (GeoJSON, KML, OSM, QGC plan/fence, ArduPilot fence): "
        "clears the waypoints, stops",
    )
    p.add_argument("id")
    p.add_argument("file", metavar="FILE")
    p.add_argument(
        "--boundary",
        metavar="SELECTOR",
        help="the boundary's features: numbers, ids, names or KEY=VALUE, comma-separated "
        "(several: their intersection)",
    )
    p.add_argument(
        "--keepouts", metavar="SELECTOR", help="the keep-outs: as --boundary, or rest, or none"
    )
    p.add_argument(
        "--boundary-bbox",
        action="store_true",
        help="the boundary is the bounding box of the file (an OSM export's bounds)",
    )
    p.add_argument(
        "--union",
        action="store_true",
        help="several boundary polygons make their union (ArduPilot's FENCE_OPTIONS), "
        "not their intersection",
    )
    p = sub.add_parser(
        "route",
        parents=[common],
        help="set the waypoints: a route file (text, JSON, GeoJSON, KML, QGC .plan, "
        ".waypoints) or LAT,LON / point names; --export FILE writes the route",
    )
    p.add_argument("id")
    p.add_argument("waypoints", nargs="*", metavar="FILE | LAT,LON")
    p.add_argument(
        "--fence", action="store_true", help="a .plan's exclusion fences become keep-outs"
    )
    p.add_argument(
        "--export", metavar="FILE", help="write the platform's route to FILE.plan or .waypoints"
    )
    p.add_argument(
        "--skip-unsupported",
        action="store_true",
        help="a mission file's commands a rover cannot do are left out (each named), "
        "instead of refusing the file",
    )
    p = sub.add_parser("patrol", parents=[common], help="the patrol's state; start or stop it")
    p.add_argument("id")
    p.add_argument("action", nargs="?", choices=["start", "stop"])
    p = sub.add_parser(
        "goto",
        parents=[common],
        help="drive to LAT,LON through the planner and stop there (patrol start resumes)",
    )
    p.add_argument("id")
    p.add_argument("point", metavar="LAT,LON")
    p = sub.add_parser(
        "logs", parents=[common], help="a platform's recordings; 'get NAME' downloads one"
    )
    p.add_argument("id")
    p.add_argument("action", nargs="?", choices=["get"])
    p.add_argument("name", nargs="?", help="the recording to download")
    p.add_argument("-o", "--output", metavar="FILE", help="where (default: NAME here)")
    p = sub.add_parser("keygen", parents=[common], help="write a new fleet key")
    p.add_argument("--path", help="where (default: the configured key file)")
    p.add_argument("--force", action="store_true", help="replace an existing key")
    return parser


COORDINATES = re.compile(r"-\d+(\.\d*)?\s*,\s*-?\d+(\.\d*)?")
"""A southern or western ``LAT,LON`` ("-36.88,174.82"), which argparse takes for an option."""


def coordinates_as_positionals(argv: Sequence[str]) -> list[str]:
    """argv with each negative ``LAT,LON`` marked positional: argparse reads a word starting
    with "-" as an option unless it is a plain number, and a "--" before it only reaches the
    top-level parser, not the command's. A leading space is not an option prefix; the
    waypoint reader strips it. A "--" before nothing that looks like an option is dropped
    (argparse's subcommand would take it for an argument)."""
    marked = [f" {arg}" if COORDINATES.fullmatch(arg) else arg for arg in argv]
    if "--" in marked:
        end = marked.index("--")
        if not any(arg.startswith("-") for arg in marked[end + 1 :]):
            del marked[end]
    return marked


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    words = sys.argv[1:] if argv is None else argv
    parser = build_parser()
    args, rest = parser.parse_known_args(coordinates_as_positionals(words))
    # argparse fills a "*" positional before an option that follows it (``route ID --json
    # WAYPOINTS``): the waypoints after the option are left over, and are still waypoints.
    if rest and isinstance(getattr(args, "waypoints", None), list):
        if not any(word.startswith("-") for word in rest):
            args.waypoints.extend(rest)
            rest = []
    if rest:
        parser.error(f"unrecognized arguments: {' '.join(rest)}")
    return args


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    setup_logging(args.verbose if args.command == "serve" else args.verbose - 1, args.log_level)
    try:
        overrides = [*args.overrides, *getattr(args, "command_overrides", [])]
        if args.insecure:
            overrides.append("security.insecure=true")
        config = load_config(StationConfig, args.config, overrides)
        return COMMANDS[args.command](args, config)
    except ConfigError as err:
        print(f"brasidas-station: {err}", file=sys.stderr)
        return 2
    except security.FleetKeyError as err:
        print(f"brasidas-station: {err}; or pass --insecure", file=sys.stderr)
        return 2
    except RpcError as err:
        print(f"brasidas-station: {_rpc_error_text(err)}", file=sys.stderr)
        return 1
    except CliError as err:
        print(f"brasidas-station: {err}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
