"""``brasidas-platform``: the robot daemon, its configuration, and the standalone simulators."""

from __future__ import annotations

import argparse
import asyncio
import functools
import importlib
import logging
import signal
import sys
from collections.abc import Sequence

from brasidas import security
from brasidas.actor import stop_on_signals
from brasidas.config import ConfigError, PlatformConfig, dump_toml, load_config
from brasidas.log import LEVELS, level_argument, setup_logging
from brasidas.sdnotify import Notifier
from platformd.mavlink.signing import SigningKeyError

_LOGGER = logging.getLogger("platformd")

SIMULATORS: dict[str, str] = {
    # name -> "module:function" of ``async def serve(config)``; prints the pty path first.
    "gps": "platformd.sim.gps:serve",
    "ax3500": "platformd.sim.ax3500:serve",
    "turret": "platformd.sim.turret:serve",
    "lidar": "platformd.sim.lidar:serve",
    "vehicle": "platformd.sim.rover:serve",  # the AX3500 and the GPS on one vehicle: 2 ptys
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="brasidas-platform", description="Brasidas platform daemon (runs on the robot)."
    )
    _add_options(parser, defaults=True)
    # The same options after the command too (`config --sim` as the docs write it); there
    # they default to nothing, so they override only what they give.
    after = argparse.ArgumentParser(add_help=False)
    _add_options(after, defaults=False)
    sub = parser.add_subparsers(dest="command")
    sub.add_parser("run", parents=[after], help="run the daemon (default)")
    sub.add_parser("config", parents=[after], help="print the effective configuration as TOML")
    check = sub.add_parser(
        "check", parents=[after], help="bring-up check: devices, keys, disk, clock (exit 1: failed)"
    )
    check.add_argument("--json", action="store_true", help="the results as JSON")
    check.add_argument(
        "--listen",
        type=_seconds,
        default=None,
        metavar="SECONDS",
        help="how long the GPS port is listened to at each baud (default 2.5)",
    )
    simulate = sub.add_parser(
        "simulate", parents=[after], help="run a simulated device on a pty, standalone"
    )
    simulate.add_argument(
        "device",
        help="device to simulate: " + ", ".join(sorted(SIMULATORS))
        if SIMULATORS
        else "device to simulate",
    )
    simulate.add_argument(
        "--carmen",
        metavar="FILE",
        help="lidar: replay a CARMEN log's scans (FLASER, ROBOTLASER1) instead of the world",
    )
    return parser


def _seconds(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not 0 < value <= 60:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds in (0, 60]")
    return value


def _add_options(parser: argparse.ArgumentParser, *, defaults: bool) -> None:
    def default(value: object) -> object:
        return value if defaults else argparse.SUPPRESS

    parser.add_argument(
        "--config", metavar="FILE", help="TOML configuration file", default=default(None)
    )
    parser.add_argument(
        "--sim",
        action="store_true",
        help="simulated hardware behind the real drivers",
        default=default(False),
    )
    parser.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=default([]),
        metavar="SECTION.KEY=VALUE",
        help="override a configuration key (repeatable)",
    )
    parser.add_argument(
        "--insecure",
        action="store_true",
        help="run without a fleet key (never in the field)",
        default=default(False),
    )
    parser.add_argument("-v", "--verbose", action="count", default=default(0), help="more logging")
    parser.add_argument(
        "--log-level",
        type=level_argument,
        help=", ".join(LEVELS),
        metavar="LEVEL",
        default=default(None),
    )


def load_platform_config(
    args: argparse.Namespace, notices: list[str] | None = None
) -> PlatformConfig:
    """The config file, ``--set`` overrides, then ``--sim`` and ``--insecure``; validated.
    Keys given by an old name are logged and appended to ``notices``."""
    flags = {"sim.enabled=true": args.sim, "security.insecure=true": args.insecure}
    overrides = [*args.overrides, *(item for item, given in flags.items() if given)]
    return load_config(PlatformConfig, args.config, overrides, notices)


def load_fleet_key(config: PlatformConfig) -> bytes | None:
    """The fleet key; created on first use in simulation, required otherwise."""
    if config.security.insecure:
        return None
    path = security.key_path(config.security.key_file)
    if config.sim.enabled:
        return security.load_or_create_key(path)
    return security.load_key(path)


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    setup_logging(args.verbose, args.log_level)
    notices: list[str] = []
    try:
        config = load_platform_config(args, notices)
    except ConfigError as err:
        print(f"brasidas-platform: {err}", file=sys.stderr)
        return 2
    command = args.command or "run"
    if command == "config":
        sys.stdout.write("".join(f"# {notice}\n" for notice in notices) + dump_toml(config))
        return 0
    if command == "simulate":
        return _simulate(args, config)
    if command == "check":
        from platformd.check import main as check_main

        if args.listen is None:
            return check_main(config, as_json=args.json)
        return check_main(config, as_json=args.json, listen_s=args.listen)
    try:
        fleet_key = load_fleet_key(config)
    except security.FleetKeyError as err:
        print(f"brasidas-platform: {err}; or pass --insecure", file=sys.stderr)
        return 2
    if fleet_key is None:
        _LOGGER.warning("running INSECURE: no fleet key, anyone on the network can connect")
    from platformd.app import load_subsystems

    load_subsystems(config)  # before the loop runs: an import there blocks it
    try:
        asyncio.run(run_daemon(config, fleet_key))
    except ConfigError as err:  # found at start: the id and URL as the beacon carries them
        print(f"brasidas-platform: {err}", file=sys.stderr)
        return 2
    except (OSError, SigningKeyError) as err:
        print(f"brasidas-platform: {err}", file=sys.stderr)
        return 1
    return 0


async def run_daemon(config: PlatformConfig, fleet_key: bytes | None) -> None:
    """Run until SIGTERM or SIGINT, then stop within a second (motors commanded to zero first).

    Under systemd, STOPPING=1 goes out from the signal handler itself, before anything else
    happens (a SIGTERM during start-up included: READY=1 then never follows).
    """
    from platformd.app import PlatformDaemon

    notifier = Notifier()
    stop = stop_on_signals(notifier.stopping)  # STOPPING=1 as soon as SIGTERM arrives
    daemon = PlatformDaemon(config, fleet_key, notifier)
    try:
        await daemon.run(stop)
    finally:
        loop = asyncio.get_running_loop()
        for signum in (signal.SIGTERM, signal.SIGINT):
            loop.remove_signal_handler(signum)
    _LOGGER.info("platform stopped")


def _simulate(args: argparse.Namespace, config: PlatformConfig) -> int:
    target = SIMULATORS.get(args.device)
    if target is None:
        known = ", ".join(sorted(SIMULATORS)) or "none"
        print(
            f"brasidas-platform: unknown device {args.device!r} (known: {known})", file=sys.stderr
        )
        return 2
    module_name, _, function_name = target.partition(":")
    serve = getattr(importlib.import_module(module_name), function_name)
    if getattr(args, "carmen", None):
        if args.device != "lidar":
            print("brasidas-platform: --carmen is for the lidar", file=sys.stderr)
            return 2
        from platformd.sim.carmen import serve_log

        serve = functools.partial(lambda log, c: serve_log(log, c.lidar), args.carmen)

    async def runner() -> None:
        stop = stop_on_signals()
        loop = asyncio.get_running_loop()
        task = loop.create_task(serve(config), name=f"simulate:{args.device}")
        waiter = loop.create_task(stop.wait())
        await asyncio.wait({task, waiter}, return_when=asyncio.FIRST_COMPLETED)
        for pending in (task, waiter):
            pending.cancel()
        await asyncio.gather(task, waiter, return_exceptions=True)

    asyncio.run(runner())
    return 0


if __name__ == "__main__":
    sys.exit(main())
