"""The on-board recorder (issue 23): what recording costs, and what it must not cost.

- ``cpu_*`` / ``bytes_per_hour_*``: a ``brasidas-platform --sim`` process (controller, GPS,
  IMU, the demo map's localization and the NavCam streaming to a station session), recorder on
  and off, at 5 fps (idle) and 30 fps (manual override engaged): process CPU time over wall
  time, and the recordings' growth scaled to an hour.
- ``loop_stall_*``: an in-process --sim platform streaming the NavCam at 30 fps: how late a
  2 ms timer fires on its event loop (p99), recorder on versus off, three alternated runs each
  (median): target < 1 ms added. On a shared, loaded machine this difference is mostly noise,
  so ``recorder_*`` also times the recorder's own loop work directly: recording every
  telemetry section (2 Hz), and queueing one bus message (the bus delivers to every
  subscriber, the recorder's callback among them).
- ``pvel_to_serial_*``: ``$PVEL`` to the first byte at the motor controller's pty
  (bench_velocity's tap), recorder on versus off: unchanged.
- ``one_hour_*``: a synthetic one-hour recording (NavCam 5 fps, every telemetry section at
  2 Hz, pose 10 Hz, GPS 1 Hz, velocities 20 Hz): opening it (summary) and seeking to a time
  (the messages of the second from there, and the keyframe before it), p50/p99 of 20 seeks.
- ``foxglove_capture_to_client_*``: NavCam capture (the platform's clock stamp) to a message
  received by a real Foxglove client (``@foxglove/ws-protocol``, Node) from the station.
"""

from __future__ import annotations

import asyncio
import json
import os
import random
import shutil
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from mcap.reader import make_reader
from mcap.writer import CompressionType, Writer

from bench import bench_velocity
from bench.support import (
    connect_to_platform,
    cpu_seconds,
    free_port,
    percentiles,
    start_platform,
    stop_process,
)
from brasidas import security, topics
from brasidas.codecs.telemetry_schema import SECTIONS
from brasidas.config import PlatformConfig, StationConfig, load_config
from brasidas.messages import Velocity
from brasidas.recording import schemas
from platformd.app import PlatformDaemon
from platformd.recorder import PlatformRecorder
from stationd.client import PlatformConnection
from stationd.daemon import StationDaemon
from stationd.foxglove_live import FoxgloveLive

PHASE_S = 20.0
STALL_S = 5.0
STALL_RUNS = 3
HOUR_S = 3600
CLIENT = Path(__file__).resolve().parent.parent / "tests" / "foxglove_client"


def _dir_bytes(directory: Path) -> int:
    return sum(p.stat().st_size for p in directory.glob("*.mcap*")) if directory.is_dir() else 0


async def _cpu_and_bytes(recorder: bool, directory: Path) -> dict[str, float]:
    signaling = free_port()
    process = await start_platform(
        f"signaling.port={signaling}",
        f"recorder.enabled={'true' if recorder else 'false'}",
        f"recorder.dir={directory}",
        "recorder.chunk_seconds=1",
        "audio.enabled=false",
    )
    tag = "on" if recorder else "off"
    figures: dict[str, float] = {}
    try:
        connection = await connect_to_platform(signaling)
        try:
            await connection.call("start_stream", name="navcam", port=free_port(2))
            await asyncio.sleep(2.0)  # start-up settles
            for fps, engaged in ((5, False), (30, True)):
                if engaged:
                    await connection.call("set_manual_override", engaged=True)
                    await asyncio.sleep(1.5)
                size0, cpu0, wall0 = (
                    _dir_bytes(directory),
                    cpu_seconds(process.pid),
                    time.monotonic(),
                )
                await asyncio.sleep(PHASE_S)
                size1, cpu1, wall1 = (
                    _dir_bytes(directory),
                    cpu_seconds(process.pid),
                    time.monotonic(),
                )
                figures[f"cpu_{fps}fps_recorder_{tag}_pct"] = round(
                    100 * (cpu1 - cpu0) / (wall1 - wall0), 2
                )
                if recorder:
                    figures[f"bytes_per_hour_{fps}fps_mb"] = round(
                        (size1 - size0) / (wall1 - wall0) * HOUR_S / 1e6, 1
                    )
            if recorder:
                listing = await connection.call("list_recordings")
                figures["recorder_dropped"] = listing["counters"]["dropped"]
                figures["recorder_written"] = listing["counters"]["written"]
        finally:
            await connection.close()
    finally:
        await stop_process(process)
    return figures


async def _loop_stalls(recorder: bool, directory: Path, key: bytes) -> list[float]:
    config = load_config(
        PlatformConfig,
        None,
        [
            "signaling.port=0",
            "velocity.port=0",
            "beacon.enabled=false",
            "audio.enabled=false",
            "sim.enabled=true",
            f"recorder.enabled={'true' if recorder else 'false'}",
            f"recorder.dir={directory}",
        ],
    )
    daemon = PlatformDaemon(config, key)
    await daemon.start()
    lateness: list[float] = []
    try:
        connection = PlatformConnection(
            config.platform.id, daemon.ctx.signaling_url, station_id="bench", fleet_key=key
        )
        await connection.open()
        try:
            await connection.call("start_stream", name="navcam", port=free_port(2))
            await connection.call("set_manual_override", engaged=True)  # 30 fps
            await asyncio.sleep(2.0)
            end = time.perf_counter() + STALL_S
            while time.perf_counter() < end:
                before = time.perf_counter()
                await asyncio.sleep(0.002)
                lateness.append((time.perf_counter() - before - 0.002) * 1000)
        finally:
            await connection.close()
    finally:
        await daemon.stop()
    return lateness


async def _recorder_loop_work(key: bytes, directory: Path) -> dict[str, float]:
    """What the recorder itself does on the event loop, timed directly (load-independent):
    a telemetry record (every section built and queued, 2 Hz) and one bus message queued."""
    config = load_config(
        PlatformConfig,
        None,
        [
            "signaling.port=0",
            "velocity.port=0",
            "beacon.enabled=false",
            "audio.enabled=false",
            "navcam.enabled=false",
            "sim.enabled=true",
            f"recorder.dir={directory}",
            "recorder.queue_messages=100000",
        ],
    )
    daemon = PlatformDaemon(config, key)
    await daemon.start()
    try:
        await asyncio.sleep(2.0)
        recorder = next(a for a in daemon.supervisor.actors if isinstance(a, PlatformRecorder))
        telemetry: list[float] = []
        for _ in range(200):
            began = time.perf_counter()
            recorder._record_telemetry()
            telemetry.append((time.perf_counter() - began) * 1000)
            await asyncio.sleep(0.005)
        message = Velocity(0.3, 0.1)
        began = time.perf_counter()
        for _ in range(5000):
            daemon.bus.publish(topics.TELEOP_VELOCITY, message)
        per_message_us = (time.perf_counter() - began) / 5000 * 1e6
    finally:
        await daemon.stop()
    result = percentiles(telemetry)
    return {
        "recorder_telemetry_record_p50_ms": result["p50"],
        "recorder_telemetry_record_p99_ms": result["p99"],
        "recorder_bus_message_us": round(per_message_us, 2),
    }


def _write_hour(path: Path) -> dict[str, int]:
    """A one-hour recording as the recorder writes it (channels, rates, sizes of a patrol)."""
    rng = random.Random(23)
    start = time.time_ns() - HOUR_S * 1_000_000_000
    with open(path, "wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD, chunk_size=4 * 1024 * 1024)
        writer.start(profile="", library="brasidas bench")
        ids: dict[str, int] = {}
        for spec in schemas.all_channels():
            schema_id = writer.register_schema(
                spec.schema_name, schemas.SCHEMA_ENCODING, spec.schema_bytes()
            )
            ids[spec.topic] = writer.register_channel(
                spec.topic, schemas.MESSAGE_ENCODING, schema_id
            )
        section = json.dumps({"field": 1.5, "other": "text", "n": 3}).encode()
        counts: dict[str, int] = {}
        step = 50_000_000  # 20 Hz ticks
        chunk_due = start + 1_000_000_000
        for tick in range(HOUR_S * 20):
            now = start + tick * step
            out: list[tuple[str, bytes]] = [
                (schemas.TELEOP_VELOCITY.topic, b'{"linear":0.3,"angular":0.1}')
            ]
            if tick % 4 == 0:  # 5 fps video: a keyframe a second
                size = 12_000 if tick % 20 == 0 else 2_500
                out.append((schemas.NAVCAM.topic, schemas.encode_video(now, rng.randbytes(size))))
            if tick % 2 == 0:
                out.append((schemas.POSE.topic, schemas.encode_location(now, 37.9, 23.6, 0, 1)))
            if tick % 10 == 0:
                out += [(schemas.TELEMETRY[cls].topic, section) for cls in SECTIONS]
            if tick % 20 == 0:
                out.append((schemas.GPS.topic, schemas.encode_location(now, 37.9, 23.6, 40, 2)))
            for topic, data in out:
                writer.add_message(ids[topic], now, data, now)
                counts[topic] = counts.get(topic, 0) + 1
            if now >= chunk_due:  # the recorder closes a chunk every second
                writer.flush()  # type: ignore[no-untyped-call]
                chunk_due += 1_000_000_000
        writer.finish()  # type: ignore[no-untyped-call]
    return counts


def _open_and_seek(path: Path) -> dict[str, Any]:
    started = time.perf_counter()
    with open(path, "rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics is not None
        first = summary.statistics.message_start_time
        opened_ms = (time.perf_counter() - started) * 1000
        seeks: list[float] = []
        rng = random.Random(5)
        for _ in range(20):
            at = first + rng.randrange(0, (HOUR_S - 2) * 1_000_000_000)
            began = time.perf_counter()
            # That second's messages, and the keyframe (the last second's first frame) before.
            frames = list(
                reader.iter_messages(
                    topics=[schemas.NAVCAM.topic], starting_at=at - 1_000_000_000, ending_at=at
                )
            )
            window = list(reader.iter_messages(starting_at=at, ending_before=at + 1_000_000_000))
            assert frames and window
            seeks.append((time.perf_counter() - began) * 1000)
    result = percentiles(seeks)
    return {
        "one_hour_file_mb": round(path.stat().st_size / 1e6, 1),
        "one_hour_open_ms": round(opened_ms, 1),
        "one_hour_seek_p50_ms": result["p50"],
        "one_hour_seek_p99_ms": result["p99"],
    }


async def _foxglove_latency(key: bytes, directory: Path) -> dict[str, Any]:
    node = shutil.which("node")
    if node is None or not (CLIENT.parent.parent / "node_modules" / "@foxglove").is_dir():
        return {"foxglove_capture_to_client": "skipped: no node client (make deps)"}
    config = load_config(
        PlatformConfig,
        None,
        [
            "platform.id=brasidas-1",
            "signaling.port=0",
            "velocity.port=0",
            "beacon.enabled=false",
            "audio.enabled=false",
            "sim.enabled=true",
            f"recorder.dir={directory}",
        ],
    )
    platform = PlatformDaemon(config, key)
    await platform.start()
    station = StationDaemon(
        load_config(StationConfig, None, ["station.api_port=0", "foxglove.port=0"]), key
    )
    await station.start()
    try:
        live = next(a for a in station.supervisor.actors if isinstance(a, FoxgloveLive))
        await asyncio.wait_for(live.serving.wait(), 30)
        await station.ctx.api.call_local(
            "connect", platform_id="brasidas-1", url=platform.ctx.signaling_url
        )
        await station.ctx.api.call_local("movrd", platform_id="brasidas-1", engaged=True)
        process = await asyncio.create_subprocess_exec(
            node,
            str(CLIENT / "subscribe.cjs"),
            f"ws://127.0.0.1:{live.port}",
            "300",
            "/navcam",  # the first platform: the recordings' names
            cwd=CLIENT,
            stdout=asyncio.subprocess.PIPE,
            stderr=asyncio.subprocess.DEVNULL,
        )
        out, _ = await asyncio.wait_for(process.communicate(), 120)
    finally:
        await station.stop()
        await platform.stop()
    samples = []
    for line in out.decode().splitlines():
        item = json.loads(line)
        if "topic" in item:
            stamp = item["json"]["timestamp"]
            captured = stamp["sec"] * 1e9 + stamp["nsec"]
            samples.append((int(item["receivedNs"]) - captured) / 1e6)
    result = percentiles(samples[30:])  # past the replayed GOP
    return {
        "foxglove_capture_to_client_p50_ms": result["p50"],
        "foxglove_capture_to_client_p99_ms": result["p99"],
        "foxglove_frames": len(samples),
    }


async def run() -> dict[str, Any]:
    figures: dict[str, Any] = {}
    key = security.load_or_create_key(security.default_key_path())
    with tempfile.TemporaryDirectory(prefix="bench-recorder-") as tmp:
        base = Path(tmp)
        figures.update(await _cpu_and_bytes(False, base / "off"))
        figures.update(await _cpu_and_bytes(True, base / "on"))
        for fps in (5, 30):
            figures[f"cpu_{fps}fps_recording_cost_pct"] = round(
                figures[f"cpu_{fps}fps_recorder_on_pct"]
                - figures[f"cpu_{fps}fps_recorder_off_pct"],
                2,
            )
        runs: dict[str, list[float]] = {"off": [], "on": []}
        for attempt in range(STALL_RUNS):  # alternated: the machine's load drifts
            for recorder in (False, True):
                tag = "on" if recorder else "off"
                lateness = await _loop_stalls(recorder, base / f"stall-{tag}-{attempt}", key)
                runs[tag].append(percentiles(lateness)["p99"])
        for tag, values in runs.items():
            figures[f"loop_stall_recorder_{tag}_p99_ms"] = statistics.median(values)
        figures["loop_stall_added_p99_ms"] = round(
            figures["loop_stall_recorder_on_p99_ms"] - figures["loop_stall_recorder_off_p99_ms"], 3
        )
        figures.update(await _recorder_loop_work(key, base / "work"))
        serial_runs: dict[str, list[dict[str, Any]]] = {"off": [], "on": []}
        for attempt in range(STALL_RUNS):  # alternated, medians: the load drifts
            for recorder in (False, True):
                tag = "on" if recorder else "off"
                serial_runs[tag].append(
                    await bench_velocity._serial_latency(
                        key,
                        (
                            f"recorder.enabled={'true' if recorder else 'false'}",
                            f"recorder.dir={base}/serial-{tag}-{attempt}",
                        ),
                    )
                )
        for tag, results in serial_runs.items():
            for q in ("p50", "p99"):
                figures[f"pvel_to_serial_20hz_recorder_{tag}_{q}_ms"] = statistics.median(
                    r[f"pvel_to_serial_20hz_{q}_ms"] for r in results
                )
        hour = base / "hour.mcap"
        started = time.monotonic()
        await asyncio.to_thread(_write_hour, hour)
        figures["one_hour_synthesis_s"] = round(time.monotonic() - started, 1)
        figures.update(await asyncio.to_thread(_open_and_seek, hour))
        os.unlink(hour)
        figures.update(await _foxglove_latency(key, base / "fx"))
    figures["target"] = "loop stall p99 added < 1 ms; serial p99 unchanged; open+seek < 1 s"
    return figures
