"""``make bench lossy``: the NavCam over a lossy, bursty, capacity-limited link (issue 28).

A platform (``--sim``: a moving test picture, 640x480 H.264) on a host behind the link
emulator, a station on the other side receiving the NavCam (``receive``: decoded at the
station, the repair path the console's feed uses) while it drives at 20 Hz with the override
engaged. Per row: frames shown (of those the camera made), time frozen, gaps between decoded
frames, glass-to-glass at the station's decoder, bitrate, the sender's retransmissions and
keyframe requests, and deadman stops (telemetry's deadman flag, sampled every 100 ms).

Rows are named ``fps{30,5}_loss{0,1,2,5,10}`` (random loss both ways), ``fps30_burst{100,300}ms``
(the link cut that long every 5 s), ``fps30_burst1500ms`` (1.5 s every ~6 s: longer than the
transport feedback stays fresh), ``fps30_cap500k`` (capacity 2 Mbit/s, dropped to 500 kbit/s
after 5 s) and ``fps30_loss{0,10}_delay20`` (20 ms each way, a mesh's hops). ``--seconds N`` (default 60) sets each row's length, ``--rows a,b``
runs only those rows (``BENCH_SECONDS``, ``BENCH_ROWS`` in the environment).
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import statistics
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from brasidas.config.platform import PlatformSection, SafetySection
from brasidas.netem.core import Profile
from brasidas.netem.netns import Host, TestNetwork, unavailable_reason
from platformd.speedcap import compute_cap

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
    delay_s: float = 0.0
    """One way, each way (a mesh's hops): the repair then costs a real round trip."""
    burst_every_s: float = BURST_EVERY_S
    """From the picture's return after one blackout to the next blackout."""


ROWS: dict[str, Row] = {
    **{f"fps30_loss{p}": Row(30, p / 100) for p in (0, 1, 2, 5, 10)},
    **{f"fps5_loss{p}": Row(5, p / 100) for p in (0, 1, 2, 5, 10)},
    "fps30_burst100ms": Row(30, burst_s=0.1),
    "fps30_burst300ms": Row(30, burst_s=0.3),
    # Longer than the transport feedback's freshness (1 s): the receiver reports decide alone
    # when the link comes back.
    "fps30_burst1500ms": Row(30, burst_s=1.5, burst_every_s=4.5),
    "fps30_cap500k": Row(30, cap_kbps=(2000, 500)),
    # A mesh's round trip (20 ms each way): glass-to-glass at 10 % loss against the same
    # link's lossless figure, the repair's round trip then the one that counts.
    "fps30_loss0_delay20": Row(30, delay_s=0.02),
    "fps30_loss10_delay20": Row(30, 0.1, delay_s=0.02),
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
    first = (
        Profile(rate_kbps=row.cap_kbps[0])
        if row.cap_kbps
        else Profile(loss=row.loss, delay=row.delay_s)
    )
    fleet.net.impair(host.name, down=first, up=first)
    sender_before = await _navcam(fleet, station, platform_id)
    await fleet.api(station, "receive", platform_id=platform_id, stream="navcam")
    # The platform's own count of deadman trips (the diagnostics section's arbiter counter):
    # a trip lasts only until the next command, shorter than telemetry's sampling.
    await fleet.api(station, "command", platform_id=platform_id, group=20, command=0, payload="ON")
    deadman = {"stops": 0, "in_blackouts": 0, "was": False, "trips": -1}
    recoveries: list[float] = []
    cut_until = [0.0]
    """While a blackout is on, time.monotonic() when its effect on commands is over."""

    sent = {"last": 0.0, "gap_max": 0.0, "window": False}

    async def drive() -> None:
        while True:
            with contextlib.suppress(RpcFailed):  # a lost answer: the next one goes on
                await fleet.api(
                    station, "teleop_set", platform_id=platform_id, linear=0.2, angular=0.0
                )
                # The driver's own pauses (this process or the station's loop starved): a
                # deadman stop after one of 0.3 s or more is the load's, not the link's.
                now = time.monotonic()
                if sent["window"] and sent["last"]:
                    sent["gap_max"] = max(sent["gap_max"], now - sent["last"])
                sent["last"] = now
            await asyncio.sleep(0.05)

    async def watch_deadman() -> None:
        while True:
            with contextlib.suppress(RpcFailed):
                report = await fleet.api(station, "get_telemetry", platform_id=platform_id)
                snapshot = report.get("snapshot") or {}
                trips = _deadman_trips(snapshot)
                if trips is not None:
                    new = trips - deadman["trips"] if deadman["trips"] >= 0 else 0
                    deadman["trips"] = trips
                else:  # no diagnostics: the flag, as sampled
                    tripped = bool((snapshot.get("motion") or {}).get("deadman"))
                    new = int(tripped and not deadman["was"])
                    deadman["was"] = tripped
                deadman["stops"] += new
                # The link cut longer than the deadman (0.3 s): the velocity stream stopped,
                # and stopping is the deadman's job; not video's doing.
                if time.monotonic() < cut_until[0]:
                    deadman["in_blackouts"] += new
            await asyncio.sleep(0.1)

    async def bursts() -> None:
        while True:
            await asyncio.sleep(row.burst_every_s)
            relay.cut()
            cut_until[0] = time.monotonic() + row.burst_s + BLACKOUT_TRIP_WINDOW_S
            await asyncio.sleep(row.burst_s)
            relay.restore()
            restored = time.monotonic()
            back = await _picture_back(fleet, station, platform_id, restored, 1000 / row.fps)
            if back is not None:
                recoveries.append(back)

    dropped_at = [0.0]
    """time.monotonic() of the capacity drop (one clock for every process on the host)."""

    async def capacity_drop() -> None:
        assert row.cap_kbps is not None
        await asyncio.sleep(CAP_DROP_AFTER_S)
        drop = Profile(rate_kbps=row.cap_kbps[1])
        fleet.net.impair(host.name, down=drop, up=drop)
        dropped_at[0] = time.monotonic()

    async with asyncio.TaskGroup() as group:
        tasks = [group.create_task(drive())]
        await asyncio.sleep(WARMUP_S)
        # A fresh receiver for the window: its gaps and latencies leave out the warm-up and
        # the framerate switch (the first frame after it needs a keyframe: a request).
        await fleet.api(station, "receive", platform_id=platform_id, stream="navcam")
        asked = time.monotonic()
        # The window starts at the fresh receiver's first frame (its start-up, the wait for a
        # first keyframe, is no loss on the link: reported on its own as first_frame_ms).
        await wait_for(lambda: _showing(fleet, station, platform_id), 10, step=0.02)
        first_frame_ms = (time.monotonic() - asked) * 1000
        tasks.append(group.create_task(watch_deadman()))
        sender_start, start = await _snapshot(fleet, station, platform_id)
        relay.stats()  # its kernel drop count restarts here
        sent["window"] = True
        started = time.monotonic()
        if row.burst_s:
            tasks.append(group.create_task(bursts()))
        if row.cap_kbps:
            tasks.append(group.create_task(capacity_drop()))
        await asyncio.sleep(seconds)
        sender_end, end = await _snapshot(fleet, station, platform_id)
        elapsed = time.monotonic() - started
        link = relay.stats()
        for task in tasks:
            task.cancel()
    relay.clear()
    frozen_cap_ms = await _cap_after_freeze(fleet, station, platform_id)
    sender = await _navcam(fleet, station, platform_id)
    await fleet.api(station, "stop_receive", platform_id=platform_id, stream="navcam")
    with contextlib.suppress(RpcFailed):
        await fleet.api(station, "movrd", platform_id=platform_id, engaged=False)
    frames = end["frames"] - start["frames"]
    encoded = sender_end.get("frames_encoded", 0) - sender_start.get("frames_encoded", 0)
    gaps = end.get("gap_ms") or {}
    repair = end.get("repair") or {}
    return {
        # Of the frames the encoder made in the window (its own counter): a frame the link
        # lost for good, or the station's receiver, is missing here; one the camera never
        # made (its real rate, the thinning under a capacity drop) is not.
        "shown_pct": round(100 * frames / encoded, 1) if encoded > 0 else None,
        "frames_shown": frames,
        "frames_encoded": encoded,
        # The encoder's frames against the nominal rate: the camera and the thinning.
        "encoded_pct": round(100 * encoded / (row.fps * elapsed), 1),
        "first_frame_ms": round(first_frame_ms),
        "frozen_pct": end.get("frozen_pct"),
        "gap_p50_ms": gaps.get("p50"),
        "gap_p95_ms": gaps.get("p95"),
        "gap_p99_ms": gaps.get("p99"),
        "gap_max_ms": gaps.get("max"),
        # What the gaps exceed the frame interval by: the part a viewer sees as a stall.
        "gap_p99_over_interval_ms": _over(gaps.get("p99"), 1000 / row.fps),
        "g2g_p50_ms": _round(end.get("latency_p50_ms")),
        "g2g_p95_ms": _round(end.get("latency_p95_ms")),
        "kbps": round((end["rtp_bytes"] - start["rtp_bytes"]) * 8 / elapsed / 1000),
        "bitrate_set_kbps": sender.get("bitrate_kbps"),
        "framerate_sent": sender.get("framerate_sent"),
        "reported_jitter_ms": sender.get("reported_jitter_ms"),
        "fec_percent": sender.get("fec_percent"),
        # In the window (as the gaps): those of the warm-up (the receiver's start on a loaded
        # machine overshot the 2 Mbit/s link now and then) are counted on their own.
        "overuses": sender_end.get("overuses", 0) - sender_start.get("overuses", 0),
        "overuses_before_window": sender_start.get("overuses", 0)
        - sender_before.get("overuses", 0),
        "transport_silences": sender_end.get("transport_silences", 0)
        - sender_start.get("transport_silences", 0),
        "transport_queue_stalls": sender_end.get("transport_queue_stalls", 0)
        - sender_start.get("transport_queue_stalls", 0),
        "reports_across_cuts": sender_end.get("reports_across_cuts", 0)
        - sender_start.get("reports_across_cuts", 0),
        "retransmissions_dropped": sender.get("retransmissions_dropped", 0)
        - sender_before.get("retransmissions_dropped", 0),
        "retransmitted": sender.get("retransmitted", 0) - sender_before.get("retransmitted", 0),
        "keyframe_requests": sender.get("keyframes_requested", 0)
        - sender_before.get("keyframes_requested", 0),
        "keyframe_requests_deferred": sender.get("keyframe_requests_deferred", 0)
        - sender_before.get("keyframe_requests_deferred", 0),
        "lost_unrepaired": repair.get("lost"),
        # Packets asked for the moment their gap arrived (the receiver's own NACK), and of
        # those the jitter buffer's own first asks let through as copies (a lossy link).
        "asked_at_once": repair.get("asked_at_once"),
        "asks_copied": repair.get("asks_copied"),
        # Packets asked for once more a round trip after the first ask (not the 33 ms retry).
        "early_reasks": repair.get("early_reasks"),
        # Keyframes the station asked at the first packet after a blackout (its frames past
        # their deadline), and the depayloader's own requests dropped as the same one.
        "keyframes_after_silence": repair.get("keyframes_after_silence"),
        "keyframe_requests_held": repair.get("keyframe_requests_held"),
        # Requests answered at once by the newest frame encoded again (not the camera's next).
        "keyframes_at_once": sender.get("keyframes_at_once", 0)
        - sender_before.get("keyframes_at_once", 0),
        "tail_copies": sender.get("tail_copies", 0) - sender_before.get("tail_copies", 0),
        # Where frames go on a perfect link under load: packets the receiver's jitter buffer
        # had to give up as too late (a frame that cannot arrive in time is dropped; and the
        # copies of frames' last packets whose first copy had passed: see tail_copies), packets
        # the emulator's sockets dropped (the kernel, its thread starved), sequence gaps seen
        # at the station's socket.
        "late_dropped": repair.get("late"),
        "link_socket_drops": link.get("socket_drops"),
        "rtp_gaps_at_receiver": end.get("rtp_lost", 0) - start.get("rtp_lost", 0),
        # Access units the depayloader made (less: dropped before the decoder, waiting for a
        # keyframe; more than shown: the decoder dropped them).
        "frames_depayloaded": end.get("frames_depayloaded", 0) - start.get("frames_depayloaded", 0),
        "deadman_stops": deadman["stops"],
        "deadman_stops_in_blackouts": deadman["in_blackouts"],
        "teleop_set_gap_max_ms": round(sent["gap_max"] * 1000),
        "cap_worst_after_freeze_ms": frozen_cap_ms,
        # Where the capacity drop's longest freeze was: at the drop (its detection, the drain
        # pause, the keyframe after it) or later (the climb back into the link, seconds on).
        "longest_freeze_began_after_drop_ms": _after_drop(end, dropped_at[0]),
        **_recovery(recoveries, row),
        "seconds": round(elapsed, 1),
        "loadavg": round(os.getloadavg()[0], 2),
    }


BLACKOUT_TRIP_WINDOW_S = 1.0
"""After a blackout, how long a deadman trip seen in telemetry is put down to it (the
telemetry that shows it crosses the link that was cut)."""


def _deadman_trips(snapshot: dict[str, Any]) -> int | None:
    subsystems = (snapshot.get("diagnostics") or {}).get("subsystems") or {}
    trips = (subsystems.get("arbiter") or {}).get("deadman_trips")
    return trips if isinstance(trips, int) else None


async def _cap_after_freeze(fleet: Fleet, station: Daemon, platform_id: str) -> float | None:
    """Freeze the picture (the stream paused, the link clean, the override still held): ms
    until the platform's speed cap is at the worst case's speed (no latency report), or None
    if not within 3 s. Measured from the pause's answer (the picture's last frame is at most a
    frame older)."""
    worst = compute_cap(SafetySection(), PlatformSection().max_speed_kmh, None, None).cap_kmh
    try:
        await fleet.api(station, "stream_pause", platform_id=platform_id, stream="navcam")
    except RpcFailed:
        return None
    paused = time.monotonic()
    try:
        while time.monotonic() - paused < 3.0:
            with contextlib.suppress(RpcFailed):
                report = await fleet.api(station, "get_telemetry", platform_id=platform_id)
                cap = ((report.get("snapshot") or {}).get("speed_cap") or {}).get("cap_kmh")
                if isinstance(cap, int | float) and cap <= worst + 0.01:
                    return round((time.monotonic() - paused) * 1000)
            await asyncio.sleep(0.02)
        return None
    finally:
        with contextlib.suppress(RpcFailed):
            await fleet.api(station, "stream_start", platform_id=platform_id, stream="navcam")


async def _showing(fleet: Fleet, station: Daemon, platform_id: str) -> bool:
    with contextlib.suppress(RpcFailed, StopIteration):
        return int((await _receiver(fleet, station, platform_id)).get("frames") or 0) > 0
    return False


SNAPSHOT_SKEW_S = 0.1
"""The longest the sender's answer may take for its frame count to pair with the receiver's
(a list_streams crosses the lossy link: a TCP retransmission can hold it 200 ms+)."""


async def _snapshot(
    fleet: Fleet, station: Daemon, platform_id: str
) -> tuple[dict[str, Any], dict[str, Any]]:
    """The sender's navcam and the station's receiver, asked at once; again while the
    sender's answer was slow, so both counts are of the same moment within ~SNAPSHOT_SKEW_S."""
    for _ in range(9):
        asked = time.monotonic()
        with contextlib.suppress(RpcFailed):
            sender, receiver = await asyncio.gather(
                _navcam(fleet, station, platform_id), _receiver(fleet, station, platform_id)
            )
            if time.monotonic() - asked <= SNAPSHOT_SKEW_S:
                return sender, receiver
    sender, receiver = await asyncio.gather(
        _navcam(fleet, station, platform_id), _receiver(fleet, station, platform_id)
    )
    return sender, receiver


async def _picture_back(
    fleet: Fleet, station: Daemon, platform_id: str, restored: float, interval_ms: float
) -> float | None:
    """After a blackout ends at ``restored`` (time.monotonic()): how long until the station
    decoded a frame captured then or later (less a frame interval: the one being made as the
    link came back), in ms; None if not within 2 s."""
    while time.monotonic() - restored < 2.0:
        await asyncio.sleep(0.01)
        with contextlib.suppress(RpcFailed):
            receiver = await _receiver(fleet, station, platform_id)
            shown_at = receiver.get("last_frame_monotonic")
            age = receiver.get("latency_ms")
            if isinstance(shown_at, float) and isinstance(age, int | float):
                captured = shown_at - age / 1000
                if captured >= restored - interval_ms / 1000:
                    return (shown_at - restored) * 1000
    return None


def _recovery(recoveries: list[float], row: Row) -> dict[str, Any]:
    """After each blackout: the picture's return, worst and median (bursts rows only)."""
    if not row.burst_s:
        return {}
    if not recoveries:
        return {"blackouts": 0}
    return {
        "blackouts": len(recoveries),
        "recovery_p50_ms": round(statistics.median(recoveries), 1),
        "recovery_max_ms": round(max(recoveries), 1),
    }


def _after_drop(receiver: dict[str, Any], dropped_at: float) -> int | None:
    """When the receiver's longest freeze began, in ms after the capacity drop (None: no
    drop in the row, or no freeze measured)."""
    ended = receiver.get("longest_freeze_ended_monotonic")
    if not dropped_at or not isinstance(ended, float):
        return None
    return round((ended - dropped_at) * 1000 - float(receiver.get("longest_freeze_ms") or 0))


def _over(gap: Any, interval_ms: float) -> float | None:
    return round(float(gap) - interval_ms, 1) if isinstance(gap, int | float) else None


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
