"""A hostile mesh (issue 19), on the test network of namespaces (root only).

A ``--sim`` platform at ``ulimit -n 1024`` (systemd's default) on one host; a station daemon
holding its manual override on another, streaming ``$PVEL`` at 20 Hz; an attacker without the
fleet key on a third (``bench/hostile_peer.py``). A probe session from the station's host
times a heartbeat every 50 ms. Three attacks, one after the other:

- the issue's unauthenticated batch flood (4 connections posting 64 KiB batches of 21,000
  ``{}`` as fast as answered, 10 s): the holder's deadman stops (the platform's log), the
  heartbeat p50/p99 before and during, the platform's RSS growth and CPU;
- 5,000 idle connections from the attacker: the time a station takes to connect meanwhile,
  the platform alive, its open descriptors against the limit;
- 1,000 connections sending half a request's headers: how many the platform closed, and
  when the last was closed (``admission.header_timeout`` 5 s).

Then issue 26's rows on loopback (:mod:`bench.hostile_round2`: replays, spoofed video, big
files); only those: ``BENCH_HOSTILE_ONLY=round2``.

Run alone: ``.venv/bin/python -m bench hostile``.
"""

from __future__ import annotations

import asyncio
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.support import cpu_seconds, percentiles, rss_mb
from brasidas import security
from brasidas.netem import mesh
from brasidas.netem.netns import BROADCAST, Host, TestNetwork, inside, unavailable_reason
from stationd.client import PlatformConnection

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from netns import API_PORT, SIGNALING_PORT, Daemon, Fleet

FD_LIMIT = 1024
FLOOD_SECONDS = 10.0
FLOOD_CONNECTIONS = 4
IDLE_CONNECTIONS = 5000
PARTIAL_CONNECTIONS = 1000
HEADER_TIMEOUT = 5.0
PROBE_INTERVAL = 0.05


async def run() -> dict[str, Any]:
    from bench import hostile_round2  # issue 26's rows, on loopback

    figures: dict[str, Any] = {}
    if os.environ.get("BENCH_HOSTILE_ONLY") != "round2":
        figures |= await _round_one()
    return figures | await hostile_round2.run()


async def _round_one() -> dict[str, Any]:
    reason = unavailable_reason()
    if reason is not None:
        return {"skipped": reason}
    with tempfile.TemporaryDirectory() as scratch, TestNetwork("hostile") as net:
        fleet = Fleet(net, Path(scratch))
        try:
            return await _attacks(net, fleet, Path(scratch))
        finally:
            fleet.stop()


async def _attacks(net: TestNetwork, fleet: Fleet, scratch: Path) -> dict[str, Any]:
    robot = net.add_host("robot")
    station_host = net.add_host("st")
    attacker = net.add_host("atk")
    log = scratch / "platform.log"
    platform = _platform(fleet, robot, log)
    station = fleet.station(station_host, "holder")
    await fleet.wait_listening(platform, robot.address, SIGNALING_PORT)
    await fleet.wait_listening(station, "127.0.0.1", API_PORT)
    await fleet.connect(station, "rover")
    if not await fleet.engage(station, "rover"):
        raise RuntimeError("the holder could not engage the override")
    url = f"http://{robot.address}:{SIGNALING_PORT}"
    probe = await _open_probe(station_host, url, fleet, "probe")
    figures: dict[str, Any] = {"fd_limit": FD_LIMIT}
    try:
        await asyncio.sleep(2.0)  # the holder's stream settles
        baseline = await _heartbeats(probe, 3.0)
        figures["heartbeat_idle_ms"] = percentiles(baseline)
        figures |= await _flood(attacker, robot, platform.process.pid, probe, log)
        figures |= await _idle(attacker, robot, platform.process.pid, station_host, url, fleet)
        figures |= await _partial(attacker, robot)
        figures["platform_alive_at_end"] = platform.process.poll() is None
        figures["out_of_resource_log_lines"] = _log_text(log).count("out of system resource")
    finally:
        await probe.close()
    return figures


def _platform(fleet: Fleet, host: Host, log: Path) -> Daemon:
    """The platform under ``prlimit --nofile=1024`` (as a default systemd unit); stopped
    with the fleet."""
    argv = mesh.platform_argv(host.address, "rover", str(fleet.key_file), (BROADCAST,))
    env = dict(os.environ, XDG_STATE_HOME=str(log.parent / "state"), PYTHONUNBUFFERED="1")
    with log.open("wb") as stderr:
        process = host.spawn(
            ["prlimit", f"--nofile={FD_LIMIT}:{FD_LIMIT}", "--", sys.executable, *argv],
            env=env,
            stderr=stderr,
        )
    daemon = Daemon(host, "rover", process, log)
    fleet.daemons.append(daemon)
    return daemon


async def _open_probe(host: Host, url: str, fleet: Fleet, station_id: str) -> PlatformConnection:
    """A session opened from ``host``'s namespace (its socket stays there)."""
    connection = PlatformConnection(
        "rover", url, station_id=station_id, fleet_key=security.load_key(fleet.key_file)
    )
    with inside(host.namespace):
        await connection.open()
    return connection


async def _heartbeats(probe: PlatformConnection, seconds: float) -> list[float]:
    """Round trips (ms) of a heartbeat every :data:`PROBE_INTERVAL` for ``seconds``."""
    samples: list[float] = []
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        started = time.perf_counter()
        await probe.call("heartbeat")
        samples.append((time.perf_counter() - started) * 1000)
        await asyncio.sleep(PROBE_INTERVAL)
    return samples


def _attack(attacker: Host, *args: object) -> subprocess.Popen[bytes]:
    return attacker.spawn(
        ["prlimit", "--nofile=16384:16384", "--", sys.executable, "-m", "bench.hostile_peer"]
        + [str(arg) for arg in args],
        stdout=subprocess.PIPE,
    )


async def _result(process: subprocess.Popen[bytes], timeout: float) -> dict[str, Any]:
    out, _ = await asyncio.to_thread(process.communicate, None, timeout)
    lines = out.decode().strip().splitlines()
    return dict(json.loads(lines[-1])) if lines else {"error": "no figures"}


def _log_text(log: Path) -> str:
    return log.read_text(errors="replace") if log.exists() else ""


async def _flood(
    attacker: Host, robot: Host, pid: int, probe: PlatformConnection, log: Path
) -> dict[str, Any]:
    deadman_before = _log_text(log).count("deadman:")
    rss_before = rss_mb(pid)
    cpu_before = cpu_seconds(pid)
    started = time.monotonic()
    flood = _attack(
        attacker, "flood", robot.address, SIGNALING_PORT, FLOOD_SECONDS, FLOOD_CONNECTIONS
    )
    rss_peak = rss_before
    samples: list[float] = []
    while flood.poll() is None and time.monotonic() - started < FLOOD_SECONDS + 10:
        samples += await _heartbeats(probe, 1.0)
        rss_peak = max(rss_peak, rss_mb(pid))
    elapsed = time.monotonic() - started
    attack = await _result(flood, 30)
    cpu = cpu_seconds(pid) - cpu_before
    return {
        "flood_requests": attack.get("requests"),
        "flood_answered_mb": round(attack.get("answered_bytes", 0) / 1e6, 2),
        "flood_deadman_stops": _log_text(log).count("deadman:") - deadman_before,
        "flood_heartbeat_ms": percentiles(samples) if samples else None,
        "flood_platform_rss_growth_mb": round(rss_peak - rss_before, 1),
        "flood_platform_cpu_percent": round(100 * cpu / elapsed, 1),
    }


async def _idle(
    attacker: Host, robot: Host, pid: int, station_host: Host, url: str, fleet: Fleet
) -> dict[str, Any]:
    idle = _attack(attacker, "idle", robot.address, SIGNALING_PORT, IDLE_CONNECTIONS, 15)
    await asyncio.sleep(5.0)  # the attacker has opened them all
    started = time.perf_counter()
    connect_s: float | str
    try:
        connection = await asyncio.wait_for(_open_probe(station_host, url, fleet, "latecomer"), 10)
    except (OSError, TimeoutError) as err:
        connect_s = f"failed: {type(err).__name__} {err}"
    else:
        connect_s = round(time.perf_counter() - started, 3)
        await connection.close()
    descriptors = len(await asyncio.to_thread(os.listdir, f"/proc/{pid}/fd"))
    attack = await _result(idle, 60)
    return {
        "idle_connections": IDLE_CONNECTIONS,
        "idle_station_connect_s": connect_s,
        "idle_platform_fds": descriptors,
        "idle_closed_by_platform": attack.get("closed_by_platform"),
    }


async def _partial(attacker: Host, robot: Host) -> dict[str, Any]:
    partial = _attack(attacker, "partial", robot.address, SIGNALING_PORT, PARTIAL_CONNECTIONS, 30)
    attack = await _result(partial, 90)
    return {
        "partial_connections": PARTIAL_CONNECTIONS,
        "partial_closed": attack.get("closed"),
        "partial_still_open_after_30s": attack.get("still_open"),
        "partial_last_closed_s": attack.get("last_closed_s"),
        "partial_header_timeout_s": HEADER_TIMEOUT,
    }
