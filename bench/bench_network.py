"""The mesh, on the test network of namespaces (root only): what a link cut costs, what a fleet
costs the station, what the mesh carries.

- link cut mid-drive → motors at zero, from the last ``$PVEL`` the link delivered to the zero
  command reaching the (simulated, pty) AX3500: p50/p99 over 20 cuts;
- link cut past ``failsafe.hold_after`` → hold: the platform's silence at the step (its
  telemetry's failsafe reason, read after the restore), over 5 cuts;
- station CPU with 20 platforms online (beacons every 3 s, from one process) and 3 connected
  (``--sim`` platforms, heartbeats and 5 Hz telemetry), over 20 s;
- what the mesh carries: beacon bytes/s per platform, telemetry bytes/s per connected pair,
  NavCam bytes/s per viewer (idle 5 fps and engaged 30 fps).

Run alone: ``.venv/bin/python -m bench network``.
"""

from __future__ import annotations

import asyncio
import contextlib
import socket
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.support import cpu_seconds, rss_mb
from brasidas.netem.beacons import BeaconFleet
from brasidas.netem.netns import BROADCAST, TestNetwork, socket_in, unavailable_reason
from brasidas.netem.relay import DOWN, parse

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from netns import (
    QUIET,
    ControllerThread,
    Daemon,
    Fleet,
    RpcFailed,
    percentile,
    wait_for,
)

CUTS = 20
HOLD_CUTS = 5
HOLD_AFTER = 1.5  # failsafe.hold_after's default
FLEET = 20
CONNECTED = 3
CPU_WINDOW = 20.0
VELOCITY_PORT = 21001


async def _link_cuts(net: TestNetwork, scratch: Path) -> dict[str, Any]:
    controller = ControllerThread()
    controller.start()
    fleet = Fleet(net, scratch / "cuts")
    try:
        station_host = net.add_host("cst")
        rover = net.add_host("crover", impaired=True)
        assert rover.relay is not None
        delivered: list[float] = []

        def tap(direction: str, frame: bytes, now: float) -> None:
            datagram = parse(frame)
            if direction == DOWN and datagram and datagram.destination[1] == VELOCITY_PORT:
                delivered.append(now)

        rover.relay.taps.append(tap)
        fleet.platform(rover, "cut-rover", *QUIET, f"motor.port={controller.path}", sim=False)
        station = fleet.station(station_host, "cut-station")
        await fleet.wait_listening(station, "127.0.0.1", 8780, timeout=40)
        await fleet.connect(station, "cut-rover", 40)
        await wait_for(lambda: fleet.engage(station, "cut-rover"), 10, step=0.2)

        async def keep_driving() -> None:
            while True:
                # Refused while a long cut has cost the station its session (until movrd).
                with contextlib.suppress(RpcFailed):
                    await fleet.api(
                        station, "teleop_set", platform_id="cut-rover", linear=0.5, angular=0.0
                    )
                await asyncio.sleep(0.1)

        def moving() -> bool:
            return bool(controller.outputs) and controller.outputs[-1][1] > 0

        latencies: list[float] = []
        holds: list[float] = []
        async with asyncio.TaskGroup() as group:
            driver = group.create_task(keep_driving())
            for _ in range(CUTS):
                await wait_for(moving, 15)
                await asyncio.sleep(0.3)
                rover.relay.cut()
                cut_at = time.monotonic()
                await wait_for(lambda: not moving(), 3, step=0.002)
                zero_at = next(t for t, speed, _ in reversed(controller.outputs) if speed == 0)
                last = max(t for t in delivered if t <= cut_at)
                latencies.append((zero_at - last) * 1000)
                rover.relay.restore()
            # Longer cuts, past failsafe.hold_after: the platform holds; its own figure for the
            # silence at the step is in telemetry's failsafe reason, read once the link is back.
            for _ in range(HOLD_CUTS):
                await wait_for(moving, 15)
                rover.relay.cut()
                await asyncio.sleep(HOLD_AFTER + 0.8)
                rover.relay.restore()
                reason = await wait_for(lambda: _held(fleet, station, "cut-rover"), 10, step=0.1)
                holds.append(float(reason.split(" for ", 1)[1].split()[0]) * 1000)
                await wait_for(lambda: fleet.engage(station, "cut-rover"), 10, step=0.2)
            driver.cancel()
        return {
            "cut_to_hold_p50_ms": round(statistics.median(holds), 1),
            "cut_to_hold_max_ms": round(max(holds), 1),
            "hold_cuts": len(holds),
            "cut_to_zero_p50_ms": round(statistics.median(latencies), 1),
            "cut_to_zero_p99_ms": round(percentile(latencies, 0.99), 1),
            "cut_to_zero_max_ms": round(max(latencies), 1),
            "cuts": len(latencies),
        }
    finally:
        fleet.stop()
        controller.close()


async def _held(fleet: Fleet, station: Daemon, platform_id: str) -> str | None:
    """The failsafe's reason while the platform holds, by its telemetry at the station."""
    report = await fleet.api(station, "get_telemetry", platform_id=platform_id)
    failsafe = report["snapshot"].get("failsafe") or {}
    return str(failsafe["reason"]) if failsafe.get("step") == "hold" else None


async def _fleet_load(net: TestNetwork, scratch: Path) -> dict[str, Any]:
    fleet = Fleet(net, scratch / "load")
    beacons: BeaconFleet | None = None
    try:
        station_host = net.add_host("lst")
        beacon_host = net.add_host("lfleet", extra_addresses=FLEET - 1)
        rovers = [net.add_host(f"lr{n}") for n in range(CONNECTED)]
        station = fleet.station(station_host, "load-station")
        ids = [f"ugv-{n:02d}" for n in range(FLEET - CONNECTED)]
        addresses = [beacon_host.address, *net.addresses_of(beacon_host, FLEET - 1)]
        beacons = BeaconFleet(
            ids,
            addresses[: len(ids)],
            fleet.key,
            BROADCAST,
            21000,
            interval=3.0,
            socket_factory=lambda: socket_in(
                beacon_host.namespace, socket.AF_INET, socket.SOCK_DGRAM
            ),
        )
        beacons.start()
        names = [f"live-{n}" for n in range(CONNECTED)]
        for host, name in zip(rovers, names, strict=True):
            fleet.platform(host, name, *QUIET[:2], "audio.enabled=false", "beacon.max_interval=3.0")
        await fleet.wait_listening(station, "127.0.0.1", 8780, timeout=40)
        for name in names:
            await fleet.connect(station, name, 40)
            await fleet.api(station, "get_telemetry", platform_id=name)

        async def all_listed() -> bool:
            return len(await fleet.api(station, "list_platforms")) == FLEET

        await wait_for(all_listed, 30, step=0.5)
        await asyncio.sleep(2)
        pid = station.process.pid
        before_cpu, before = cpu_seconds(pid), time.monotonic()
        telemetry_before = [
            (await fleet.api(station, "get_telemetry", platform_id=n))["link"]["bytes_received"]
            for n in names
        ]
        sent_before = beacons.bytes_sent, beacons.sent
        await asyncio.sleep(CPU_WINDOW)
        elapsed = time.monotonic() - before
        cpu = (cpu_seconds(pid) - before_cpu) / elapsed
        telemetry_after = [
            (await fleet.api(station, "get_telemetry", platform_id=n))["link"]["bytes_received"]
            for n in names
        ]
        telemetry_rate = [
            (a - b) / elapsed for a, b in zip(telemetry_after, telemetry_before, strict=True)
        ]
        beacon_bytes = beacons.bytes_sent - sent_before[0]
        listed = len(await fleet.api(station, "list_platforms"))

        # Video per viewer: the NavCam of one platform, idle (5 fps) then engaged (30 fps).
        video = await _video_rates(fleet, station, names[0])
        return {
            "station_cpu_pct_of_one_core": round(cpu * 100, 2),
            "station_rss_mb": rss_mb(pid),
            "platforms_listed": listed,
            "platforms_connected": CONNECTED,
            "beacon_bytes_per_s_per_platform_idle": round(beacon_bytes / elapsed / len(ids), 1),
            "beacon_bytes_each": round(beacons.bytes_sent / max(1, beacons.sent)),
            "telemetry_bytes_per_s_per_pair": round(statistics.median(telemetry_rate)),
            **video,
        }
    finally:
        if beacons is not None:
            beacons.close()
        fleet.stop()


async def _video_rates(fleet: Fleet, station: Daemon, name: str) -> dict[str, Any]:
    # The first platform was started with its NavCam (QUIET[:2] leaves navcam on).
    await fleet.api(station, "receive", platform_id=name, stream="navcam")

    async def rate(seconds: float) -> float:
        async def rtp_bytes() -> int:
            receivers = await fleet.api(station, "receivers")
            return int(next(r for r in receivers if "navcam" in r["name"])["rtp_bytes"])

        start = await rtp_bytes()
        await asyncio.sleep(seconds)
        return (await rtp_bytes() - start) / seconds

    await asyncio.sleep(3)
    idle = await rate(5)
    await wait_for(lambda: fleet.engage(station, name), 10, step=0.2)
    await asyncio.sleep(3)
    engaged = await rate(5)
    await fleet.api(station, "stop_receive", platform_id=name, stream="navcam")
    return {
        "navcam_bytes_per_s_per_viewer_idle_5fps": round(idle),
        "navcam_bytes_per_s_per_viewer_engaged_30fps": round(engaged),
    }


async def run() -> dict[str, Any]:
    reason = unavailable_reason()
    if reason is not None:
        return {"skipped": reason}
    scratch = Path(tempfile.mkdtemp(prefix="brasidas-bench-network-"))
    with TestNetwork("bench") as net:
        cuts = await _link_cuts(net, scratch)
        load = await _fleet_load(net, scratch)
    return {**cuts, **load}
