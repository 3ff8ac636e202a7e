"""``make bench lossy``: the NavCam over a lossy, bursty, capacity-limited link (issue 28).

A platform (``--sim``: a moving test picture, 640x480 H.264) on a host behind the link
emulator, a station on the other side receiving the NavCam (``receive``: decoded at the
station, the repair path the console's feed uses) while it drives at 20 Hz with the override
engaged. Per row: frames shown (of those the camera made), time frozen, gaps between decoded
frames, glass-to-glass at the station's decoder, bitrate, the sender's retransmissions and
keyframe requests, and deadman stops (telemetry's deadman flag, sampled every 100 ms).

Rows are named ``fps{30,5}_loss{0,1,2,5,10}`` (random loss both ways), ``fps30_burst{100,300}ms``
(the link cut that long every 5 s) and ``fps30_cap500k`` (capacity 2 Mbit/s, dropped to
500 kbit/s after 5 s). ``--seconds N`` (default 60) sets each row's length, ``--rows a,b``
runs only those rows (``BENCH_SECONDS``, ``BENCH_ROWS`` in the environment).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from brasidas.netem.core import Profile
from brasidas.netem.netns import Host, TestNetwork, unavailable_reason

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from netns import Daemon, Fleet, RpcFailed, wait_for

SECONDS = float(os.environ.get("BENCH_SECONDS", "60"))
WARMUP_S = 3.0
BURST_EVERY_S = 5.0
CAP_DROP_AFTER_S = 5.0
PLATFORM_SETTINGS = [word for word in os.environ.get("BENCH_PLATFORM_SET", "").split(",") if word]
"""Extra platform settings for every row (``BENCH_PLATFORM_SET=navcam.intra_refresh=true``)."""


@dataclass(frozen=True)
class Row:
    fps: int
    loss: float = 0.0
    burst_s: float = 0.0
    cap_kbps: tuple[float, float] | None = None
    """Capacity before and after the drop."""


ROWS: dict[str, Row] = {
    **{f"fps30_loss{p}": Row(30, p / 100) for p in (0, 1, 2, 5, 10)},
    **{f"fps5_loss{p}": Row(5, p / 100) for p in (0, 1, 2, 5, 10)},
    "fps30_burst100ms": Row(30, burst_s=0.1),
    "fps30_burst300ms": Row(30, burst_s=0.3),
    "fps30_cap500k": Row(30, cap_kbps=(2000, 500)),
}


def _selected() -> list[str]:
    wanted = [name for name in os.environ.get("BENCH_ROWS", "").split(",") if name]
    unknown = [name for name in wanted if name not in ROWS]
    if unknown:
        raise ValueError(f"unknown rows {unknown} (rows: {', '.join(ROWS)})")
    return wanted or list(ROWS)


async def _receiver(fleet: Fleet, station: Daemon, platform_id: str) -> dict[str, Any]:
    receivers = await fleet.api(station, "receivers")
    found: dict[str, Any] = next(r for r in receivers if r["platform_id"] == platform_id)
    return found


async def _navcam(fleet: Fleet, station: Daemon, platform_id: str) -> dict[str, Any]:
    streams = await fleet.api(station, "streams", platform_id=platform_id)
    found: dict[str, Any] = next(s for s in streams if s["name"] == "navcam")
    return found


async def _row(
    fleet: Fleet, station: Daemon, host: Host, platform_id: str, row: Row, seconds: float
) -> dict[str, Any]:
    relay = host.relay
    assert relay is not None
    relay.clear()
    await fleet.connect(station, platform_id, 40)
    await wait_for(lambda: fleet.engage(station, platform_id), 15, step=0.2)
    # The camera runs at 30 fps; 10.5 sets the engaged mode's rate (5 fps: a sixth the bits).
    await fleet.api(
        station,
        "command",
        platform_id=platform_id,
        group=10,
        command=5,
        payload=f"navcam={row.fps}",
    )
    first = Profile(rate_kbps=row.cap_kbps[0]) if row.cap_kbps else Profile(loss=row.loss)
    fleet.net.impair(host.name, down=first, up=first)
    sender_before = await _navcam(fleet, station, platform_id)
    await fleet.api(station, "receive", platform_id=platform_id, stream="navcam")
    deadman = {"stops": 0, "was": False}

    async def drive() -> None:
        while True:
            with contextlib.suppress(RpcFailed):  # a lost answer: the next one goes on
                await fleet.api(
                    station, "teleop_set", platform_id=platform_id, linear=0.2, angular=0.0
                )
            await asyncio.sleep(0.05)

    async def watch_deadman() -> None:
        while True:
            with contextlib.suppress(RpcFailed):
                report = await fleet.api(station, "get_telemetry", platform_id=platform_id)
                tripped = bool(((report.get("snapshot") or {}).get("motion") or {}).get("deadman"))
                deadman["stops"] += tripped and not deadman["was"]
                deadman["was"] = tripped
            await asyncio.sleep(0.1)

    async def bursts() -> None:
        while True:
            await asyncio.sleep(BURST_EVERY_S)
            relay.cut()
            await asyncio.sleep(row.burst_s)
            relay.restore()

    async def capacity_drop() -> None:
        assert row.cap_kbps is not None
        await asyncio.sleep(CAP_DROP_AFTER_S)
        drop = Profile(rate_kbps=row.cap_kbps[1])
        fleet.net.impair(host.name, down=drop, up=drop)

    async with asyncio.TaskGroup() as group:
        tasks = [group.create_task(drive())]
        await asyncio.sleep(WARMUP_S)
        # A fresh receiver for the window: its gaps and latencies leave out the warm-up and
        # the framerate switch (the first frame after it needs a keyframe: a request).
        await fleet.api(station, "receive", platform_id=platform_id, stream="navcam")
        tasks.append(group.create_task(watch_deadman()))
        start = await _receiver(fleet, station, platform_id)
        started = time.monotonic()
        if row.burst_s:
            tasks.append(group.create_task(bursts()))
        if row.cap_kbps:
            tasks.append(group.create_task(capacity_drop()))
        await asyncio.sleep(seconds)
        end = await _receiver(fleet, station, platform_id)
        elapsed = time.monotonic() - started
        for task in tasks:
            task.cancel()
    relay.clear()
    sender = await _navcam(fleet, station, platform_id)
    await fleet.api(station, "stop_receive", platform_id=platform_id, stream="navcam")
    with contextlib.suppress(RpcFailed):
        await fleet.api(station, "movrd", platform_id=platform_id, engaged=False)
    frames = end["frames"] - start["frames"]
    gaps = end.get("gap_ms") or {}
    repair = end.get("repair") or {}
    return {
        "shown_pct": round(100 * frames / (row.fps * elapsed), 1),
        "frozen_pct": end.get("frozen_pct"),
        "gap_p50_ms": gaps.get("p50"),
        "gap_p95_ms": gaps.get("p95"),
        "gap_p99_ms": gaps.get("p99"),
        "gap_max_ms": gaps.get("max"),
        "g2g_p50_ms": _round(end.get("latency_p50_ms")),
        "g2g_p95_ms": _round(end.get("latency_p95_ms")),
        "kbps": round((end["rtp_bytes"] - start["rtp_bytes"]) * 8 / elapsed / 1000),
        "bitrate_set_kbps": sender.get("bitrate_kbps"),
        "framerate_sent": sender.get("framerate_sent"),
        "reported_jitter_ms": sender.get("reported_jitter_ms"),
        "fec_percent": sender.get("fec_percent"),
        "overuses": sender.get("overuses", 0) - sender_before.get("overuses", 0),
        "retransmissions_dropped": sender.get("retransmissions_dropped", 0)
        - sender_before.get("retransmissions_dropped", 0),
        "retransmitted": sender.get("retransmitted", 0) - sender_before.get("retransmitted", 0),
        "keyframe_requests": sender.get("keyframes_requested", 0)
        - sender_before.get("keyframes_requested", 0),
        "lost_unrepaired": repair.get("lost"),
        "deadman_stops": deadman["stops"],
        "seconds": round(elapsed, 1),
        "loadavg": round(os.getloadavg()[0], 2),
    }


def _round(value: Any) -> float | None:
    return round(float(value), 1) if isinstance(value, int | float) else None


async def run() -> dict[str, Any]:
    reason = unavailable_reason()
    if reason is not None:
        return {"skipped": reason}
    names = _selected()
    scratch = Path(tempfile.mkdtemp(prefix="brasidas-bench-lossy-"))
    results: dict[str, Any] = {}
    with TestNetwork("lossy") as net:
        fleet = Fleet(net, scratch)
        try:
            station_host = net.add_host("lst")
            hosts: dict[int, Host] = {}
            for fps in sorted({ROWS[name].fps for name in names}):
                host = hosts[fps] = net.add_host(f"lr{fps}", impaired=True)
                fleet.platform(
                    host,
                    f"lossy-{fps}",
                    "gps.enabled=false",
                    "imu.enabled=false",
                    "audio.enabled=false",
                    "recorder.enabled=false",
                    "navcam.framerate=30",
                    f"navcam.idle_framerate={fps}",
                    "navcam.sim_pattern=smpte",
                    "navcam.sim_motion=4",
                    *PLATFORM_SETTINGS,
                )
            station = fleet.station(station_host, "lossy-station")
            await fleet.wait_listening(station, "127.0.0.1", 8780, timeout=40)
            for name in names:
                row = ROWS[name]
                platform_id = f"lossy-{row.fps}"
                results[name] = await _row(
                    fleet, station, hosts[row.fps], platform_id, row, SECONDS
                )
                print(f"   {name}: {results[name]}", flush=True)
        finally:
            fleet.stop()
    return results
