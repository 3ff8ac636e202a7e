"""``make demo``: a simulated platform and a station daemon on loopback, connected.

Runs both daemons as child processes (exactly as an operator would), waits until the station
discovers the platform, connects, prints what it got and what to try next, and keeps running
until Ctrl-C, when it stops both cleanly.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import sys
import time
from pathlib import Path
from typing import Any

from brasidas import security
from brasidas.actor import stop_on_signals
from brasidas.codecs.jsonrpc import RpcError
from brasidas.config import StationConfig, load_config
from stationd.api_client import CliError, api_call_async
from stationd.cli import describe_connection


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(prog="brasidas-demo", description=__doc__)
    parser.add_argument("--platform-id", default="brasidas-sim")
    parser.add_argument("--signaling-port", type=int, default=8765)
    parser.add_argument("--api-port", type=int, default=8780)
    parser.add_argument("--beacon-port", type=int, default=21000)
    parser.add_argument("--velocity-port", type=int, default=21001)
    parser.add_argument(
        "--mavlink-target",
        default="127.0.0.1:14550",
        help="where the MAVLink endpoint sends (QGroundControl listens on UDP 14550)",
    )
    parser.add_argument(
        "--mavlink-port", type=int, default=14555, help="UDP port the MAVLink endpoint listens on"
    )
    parser.add_argument("--once", action="store_true", help="stop after connecting (for tests)")
    parser.add_argument("--timeout", type=float, default=15.0, help="seconds to wait for discovery")
    return parser.parse_args(argv)


async def run(args: argparse.Namespace) -> int:
    key_path = security.default_key_path()
    security.load_or_create_key(key_path)
    log_dir = security.state_dir() / "demo"
    log_dir.mkdir(parents=True, exist_ok=True)
    python = sys.executable
    platform_cmd = [
        python,
        "-m",
        "platformd",
        "--sim",
        "--set",
        f"platform.id={args.platform_id}",
        "--set",
        f"signaling.port={args.signaling_port}",
        "--set",
        f"beacon.port={args.beacon_port}",
        "--set",
        f"velocity.port={args.velocity_port}",
        # The MAVLink endpoint for ground control stations (docs/integrations.md):
        # on loopback only, so unsigned control costs nothing here.
        "--set",
        "mavlink.enabled=true",
        "--set",
        f'mavlink.targets=["{args.mavlink_target}"]',
        "--set",
        f"mavlink.port={args.mavlink_port}",
        "--set",
        "mavlink.allow_unsigned_control=true",
    ]
    station_overrides = [
        "--set",
        f"station.api_port={args.api_port}",
        "--set",
        f"discovery.port={args.beacon_port}",
    ]
    station_cmd = [python, "-m", "stationd", "serve", *station_overrides]
    config = load_config(StationConfig, None, station_overrides[1::2])

    processes: list[asyncio.subprocess.Process] = []
    started = time.monotonic()
    try:
        for name, cmd in (("platform", platform_cmd), ("station", station_cmd)):
            # A local log file opens at once; the child writes it, not this loop.
            log = open(log_dir / f"{name}.log", "wb")  # noqa: ASYNC230
            processes.append(
                await asyncio.create_subprocess_exec(
                    *cmd, stdout=log, stderr=log, start_new_session=True
                )
            )
            log.close()
        print(f"Starting a simulated platform and a station (logs in {log_dir}) ...", flush=True)
        summary = await _discover_and_connect(config, args, processes)
        print(f"\nDiscovered and connected in {time.monotonic() - started:.1f} s:\n")
        print(describe_connection(summary))
        print(_ground_station_line(args), flush=True)
        if args.once:
            return 0
        _print_next_steps(args)
        await _wait_for_interrupt(processes)
        return 0
    except (CliError, RpcError, TimeoutError) as err:
        message = err.message if isinstance(err, RpcError) else str(err) or "timed out"
        print(f"demo: {message}; see the logs in {log_dir}", file=sys.stderr)
        for name in ("platform", "station"):
            tail = (log_dir / f"{name}.log").read_text(errors="replace").splitlines()[-5:]
            print(f"--- {name}.log (last lines)\n" + "\n".join(tail), file=sys.stderr)
        return 1
    finally:
        await _stop(processes)


async def _discover_and_connect(
    config: StationConfig, args: argparse.Namespace, processes: list[asyncio.subprocess.Process]
) -> dict[str, Any]:
    deadline = time.monotonic() + args.timeout
    while True:
        for process in processes:
            if process.returncode is not None:
                raise CliError(f"a daemon exited early (status {process.returncode})")
        try:
            platforms = await api_call_async(config, "list_platforms")
            if any(entry.get("id") == args.platform_id for entry in platforms):
                print(
                    f"Station discovered platform {args.platform_id!r} from its beacon.", flush=True
                )
                summary: dict[str, Any] = await api_call_async(
                    config, "connect", platform_id=args.platform_id
                )
                return summary
        except (CliError, RpcError):
            pass  # daemons still starting
        if time.monotonic() > deadline:
            raise TimeoutError(
                f"platform {args.platform_id} not discovered within {args.timeout:.0f} s"
            )
        await asyncio.sleep(0.2)


def _print_next_steps(args: argparse.Namespace) -> None:
    station = "brasidas-station" if _on_path("brasidas-station") else ".venv/bin/brasidas-station"
    pid = args.platform_id
    tries = [
        ("list", "platforms online, from their beacons"),
        (f"status {pid}", "parameters, mode, telemetry"),
        (f"status {pid} --watch", "live telemetry with the annunciator"),
        (f"drive {pid}", "keyboard teleop: arrows/WASD, space stops, q quits"),
        (f"view {pid}", "the NavCam video in a window, with its latency"),
        (f"view {pid} --sdp navcam.sdp", "an SDP file for ffplay or VLC"),
        (f"audio {pid} --talk", "hear the platform's microphone, talk back"),
        (f"movrd {pid} on|off", "manual override (teleop / autonomous)"),
        (f"patrol {pid} start", "patrol the demo loop around the shed (patrol: its state)"),
        (f"route {pid} sw ne sw", "new waypoints on the fly (named points or LAT,LON)"),
        (
            f"route {pid} --export patrol.plan",
            "the route as a QGroundControl plan (.waypoints too)",
        ),
        (f"logs {pid}", "the platform's recordings (MCAP); logs ID get NAME downloads one"),
        (f"lights {pid} main on", "main lights (10.6)"),
        (f"cmd {pid} 10 5 navcam=10", "any system command of table 10.1"),
    ]
    width = max(len(command) for command, _ in tries)
    lines = "\n".join(f"  {station} {command:<{width}}  # {what}" for command, what in tries)
    print(
        "\nThe demo is running. In another terminal (from this directory), try:\n\n"
        f"{lines}\n\n"
        f"Browser console: http://127.0.0.1:{args.api_port}/  (the whole station: map, NavCam,"
        " driving with keys or a game controller, audio, patrol, telemetry and warnings)\n"
        f"Station API: http://127.0.0.1:{args.api_port}/api/rpc   "
        f"Platform signaling: http://127.0.0.1:{args.signaling_port}/rpc\n"
        "Foxglove or Lichtblick: open a Foxglove WebSocket connection to ws://127.0.0.1:8766 "
        "(the live fleet, read-only); a downloaded recording opens as a file.\n"
        "Press Ctrl-C to stop both daemons.",
        flush=True,
    )


def _ground_station_line(args: argparse.Namespace) -> str:
    """How to open the platform in a MAVLink ground control station."""
    port = args.mavlink_target.rpartition(":")[2]
    return (
        f"\nGround control station: open QGroundControl (it listens on UDP {port}); the rover "
        f"'{args.platform_id}' appears as MAVLink system 1, mode HOLD. Or: "
        f"mavproxy.py --master=udpin:127.0.0.1:{port}, or MAVSDK with udpin://127.0.0.1:{port}"
        f" (the endpoint listens on UDP {args.mavlink_port})."
    )


def _on_path(name: str) -> bool:
    return any(Path(d, name).exists() for d in os.environ.get("PATH", "").split(os.pathsep))


async def _wait_for_interrupt(processes: list[asyncio.subprocess.Process]) -> None:
    stop = stop_on_signals()
    loop = asyncio.get_running_loop()
    waiters = [loop.create_task(p.wait()) for p in processes]
    stopper = loop.create_task(stop.wait())
    done, _ = await asyncio.wait([stopper, *waiters], return_when=asyncio.FIRST_COMPLETED)
    for task in [stopper, *waiters]:
        task.cancel()
    await asyncio.gather(stopper, *waiters, return_exceptions=True)
    if stopper not in done:
        print("demo: a daemon exited; stopping", file=sys.stderr)
    print("\nStopping ...", flush=True)


async def _stop(processes: list[asyncio.subprocess.Process]) -> None:
    # The station first: its goodbye releases the override before the platform goes down.
    for process in reversed(processes):
        if process.returncode is None:
            process.send_signal(signal.SIGTERM)
            try:
                await asyncio.wait_for(process.wait(), 3)
            except TimeoutError:
                process.kill()
                await process.wait()


def main(argv: list[str] | None = None) -> int:
    return asyncio.run(run(parse_args(argv)))


if __name__ == "__main__":
    sys.exit(main())
