"""Memory: the resident set of a busy ``--sim`` platform over time, idle and streaming the NavCam.

The platform (a child process, :mod:`bench.memory_probe`) has one station daemon connected
(telemetry streaming to it), the manual override engaged and a 10 Hz teleop setpoint going in;
once with the NavCam streaming at 30 fps to the station (decoded into a fakesink). After a
warm-up its RSS is sampled every few seconds and the least-squares slope is extrapolated to an
hour (target < 1 MB an hour), with where the memory is: glibc malloc in use, the bytes pymalloc
has handed out (Python's small objects) and, of those, what CPython keeps on its free lists.

What the figure used to show (5.7-8.3 MB/h after 150 s) was CPython 3.11's tuple free lists
filling up: ``dataclasses.fields()`` per telemetry section, 5 times a second, built each tuple
from a generator (made with 10 slots, shrunk, freed onto the free list of its final size), so
nine free lists grew by ~100 tuples a second to their cap of 2000 each: +1.2 MB of pymalloc
blocks over the first 8 minutes, then flat (a 20-minute run, idle and streaming alike). Bounded,
but it is what a slope over minutes 2.5-6 measured. The schema now looks fields up once. The
warm-up (``BENCH_MEMORY_WARMUP_S``, 120 s) covers the start: the session, the streams, the first
GPS fix, imports done lazily; the window (``BENCH_MEMORY_SECONDS``, 240 s) can be made as long
as wanted for a long-run figure, e.g. ``BENCH_MEMORY_SECONDS=1500 python -m bench memory``.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import os
import socket
import sys
import time
import tracemalloc
from collections.abc import AsyncIterator
from dataclasses import dataclass, field
from typing import Any

from bench.support import PLATFORM_LOG, free_port, station_connect, stop_process, wait_ready
from brasidas import security
from brasidas.codecs.jsonrpc import RpcError
from brasidas.config import StationConfig, load_config
from stationd.daemon import StationDaemon

RESULTS = PLATFORM_LOG.parent
"""Where each run's samples go (``memory_idle.jsonl``, ``memory_navcam.jsonl``: every line the
probe printed, warm-up included)."""
WARMUP_S = float(os.environ.get("BENCH_MEMORY_WARMUP_S", "120"))
MEASURE_S = float(os.environ.get("BENCH_MEMORY_SECONDS", "240"))
INTERVAL_S = 5.0


@dataclass
class Samples:
    """What the probe reported: (monotonic s, RSS KiB, Python-traced bytes or 0)."""

    lines: list[tuple[float, int, int]] = field(default_factory=list)
    raw: list[dict[str, Any]] = field(default_factory=list)
    process: asyncio.subprocess.Process | None = None
    dumped: asyncio.Queue[str] = field(default_factory=asyncio.Queue)
    tracing: asyncio.Event = field(default_factory=asyncio.Event)

    async def trace(self, timeout: float = 30.0) -> None:
        """Have the platform start tracemalloc now (``trace_when_told``)."""
        assert self.process is not None and self.process.stdin is not None
        self.process.stdin.write(b"trace\n")
        await self.process.stdin.drain()
        async with asyncio.timeout(timeout):
            await self.tracing.wait()

    async def snapshot(self, path: str, timeout: float = 60.0) -> str:
        """Have the platform dump a tracemalloc snapshot (needs ``frames`` > 0)."""
        assert self.process is not None and self.process.stdin is not None
        self.process.stdin.write(f"snapshot {path}\n".encode())
        await self.process.stdin.drain()
        async with asyncio.timeout(timeout):
            return await self.dumped.get()

    def since(self, start: float) -> list[tuple[float, int, int]]:
        return [line for line in self.lines if line[0] >= start]


_NOT_THE_PLATFORM = ("<frozen importlib", "tracemalloc.py", "linecache.py", "memory_probe.py")


def load_snapshot(path: str) -> tracemalloc.Snapshot:
    """A dumped snapshot without the allocations of importing, tracing and probing."""
    return tracemalloc.Snapshot.load(path).filter_traces(
        [tracemalloc.Filter(False, f"*{name}*") for name in _NOT_THE_PLATFORM]
    )


def steady_growth(snapshots: list[tracemalloc.Snapshot]) -> list[tuple[str, int]]:
    """Allocation sites (file:line) that held more at every snapshot than at the one before,
    with what they gained from the first to the last, largest first. Transient allocations
    (a message in flight, a buffer) come and go; a leak only grows."""
    sizes = [
        {str(stat.traceback[0]): stat.size for stat in snapshot.statistics("lineno")}
        for snapshot in snapshots
    ]
    grown = []
    for site in sizes[-1]:
        held = [by_site.get(site, 0) for by_site in sizes]
        if all(later > earlier for earlier, later in itertools.pairwise(held)):
            grown.append((site, held[-1] - held[0]))
    return sorted(grown, key=lambda item: -item[1])


def slope_per_hour(points: list[tuple[float, float]]) -> float:
    """Least-squares slope of (seconds, value) points, per hour."""
    n = len(points)
    if n < 2:
        raise ValueError("need two points for a slope")
    mean_t = sum(t for t, _ in points) / n
    mean_v = sum(v for _, v in points) / n
    num = sum((t - mean_t) * (v - mean_v) for t, v in points)
    den = sum((t - mean_t) ** 2 for t, _ in points)
    return num / den * 3600.0


@contextlib.asynccontextmanager
async def busy_platform(
    *,
    navcam: bool = False,
    frames: int = 0,
    interval: float = INTERVAL_S,
    report: str = "",
    baseline: float = WARMUP_S,
    extra: tuple[str, ...] = (),
    trim: bool = False,
    collect: bool = False,
    mallocstats: bool = False,
    trace_from: float = 0.0,
    trace_when_told: bool = False,
    env: dict[str, str] | None = None,
) -> AsyncIterator[Samples]:
    """A ``--sim`` platform made busy by a station; yields its memory samples as they come
    (``trace_when_told``: tracemalloc starts at :meth:`Samples.trace`, not with the process)."""
    signaling = free_port()
    args = [
        sys.executable, "-m", "bench.memory_probe",
        f"--interval={interval}", f"--frames={frames}", f"--baseline={baseline}",
    ]  # fmt: skip
    if report:
        args.append(f"--report={report}")
    if trim:
        args.append("--trim")
    if collect:
        args.append("--collect")
    if mallocstats:
        args.append("--mallocstats")
    if trace_from:
        args.append(f"--trace-from={trace_from}")
    if trace_when_told:
        args.append("--trace-when-told")
    args += ["--", "--sim"]
    for item in (
        f"signaling.port={signaling}",
        f"beacon.port={free_port(socket.SOCK_DGRAM)}",
        f"velocity.port={free_port(socket.SOCK_DGRAM)}",
        *extra,
    ):
        args += ["--set", item]
    PLATFORM_LOG.parent.mkdir(exist_ok=True)
    with PLATFORM_LOG.open("ab") as log:
        process = await asyncio.create_subprocess_exec(
            *args,
            stdin=asyncio.subprocess.PIPE,
            stdout=asyncio.subprocess.PIPE,
            stderr=log,
            env=None if env is None else {**os.environ, **env},
        )
    samples = Samples(process=process)

    async def read() -> None:
        assert process.stdout is not None
        async for raw in process.stdout:
            try:
                line = json.loads(raw)
            except ValueError:
                continue  # not the probe's (a library printing)
            if "snapshot" in line:
                samples.dumped.put_nowait(line["snapshot"])
            elif "tracing" in line:
                samples.tracing.set()
            else:
                samples.raw.append(line)
                samples.lines.append((line["t"], line["rss_kb"], line.get("traced", 0)))

    key = security.load_or_create_key(security.default_key_path())
    station = StationDaemon(load_config(StationConfig, None, ["station.api_port=0"]), key)
    try:
        async with asyncio.TaskGroup() as group:
            reader = group.create_task(read())
            await station.start()
            try:
                api = station.ctx.api
                await wait_ready(signaling, timeout=120.0)  # tracemalloc slows the start
                await station_connect(api, f"http://127.0.0.1:{signaling}")
                answer = await api.call_local("movrd", platform_id="brasidas-1", engaged=True)
                if not answer.get("accepted"):
                    raise RuntimeError(f"manual override refused: {answer}")
                if navcam:
                    await api.call_local("receive", platform_id="brasidas-1", stream="navcam")
                teleop = group.create_task(_teleop(api))
                try:
                    yield samples
                finally:
                    teleop.cancel()
            finally:
                await station.stop()
                await stop_process(process)
                reader.cancel()
    finally:
        await stop_process(process, 0.0)


async def _teleop(api: Any) -> None:
    """What the keyboard client does: a setpoint every 100 ms, gently changing."""
    step = 0
    while True:
        step += 1
        linear = 0.3 if step % 50 < 25 else -0.2
        with contextlib.suppress(RpcError):  # a session lost under load comes back
            await api.call_local("teleop_set", platform_id="brasidas-1", linear=linear, angular=0.1)
        await asyncio.sleep(0.1)


async def rss_growth(
    navcam: bool, warmup: float = WARMUP_S, measure: float = MEASURE_S
) -> dict[str, float]:
    """After ``warmup``, over ``measure`` seconds: the RSS slope (MB an hour) and the total
    growth (MB), and where it is: the slopes of what glibc malloc holds in use (all arenas) and
    of the bytes pymalloc has handed out (Python's small objects, in 1 MiB mmap'd arenas that
    neither malloc's figures nor ``malloc_trim`` touch), and how much CPython's free lists (part
    of pymalloc's bytes) held at the end and gained over the window; of the file pages (code run
    for the first time); and what malloc holds free (a burst's high-water mark: under load the
    NavCam's buffers pile up once, are freed, and the pages stay: +2 MB seen once, read as
    34 MB/h over 4 minutes, with malloc's bytes in use and Python's flat)."""
    async with busy_platform(navcam=navcam, mallocstats=True) as samples:
        start = time.monotonic() + warmup  # the probe's clock: CLOCK_MONOTONIC, system-wide
        await asyncio.sleep(warmup + measure)
        lines = [line for line in samples.raw if line["t"] >= start]
    RESULTS.mkdir(exist_ok=True)
    with (RESULTS / f"memory_{'navcam' if navcam else 'idle'}.jsonl").open("w") as out:
        out.writelines(json.dumps(line) + "\n" for line in samples.raw)
    return {
        "rss_mb_per_h": slope_per_hour([(line["t"], line["rss_kb"] / 1024) for line in lines]),
        "rss_total_mb": (lines[-1]["rss_kb"] - lines[0]["rss_kb"]) / 1024,
        "rss_file_mb_per_h": slope_per_hour(
            [(line["t"], line["rss_file_kb"] / 1024) for line in lines]
        ),
        "malloc_in_use_mb_per_h": slope_per_hour(
            [(line["t"], line["m_inuse_kb"] / 1024) for line in lines]
        ),
        "malloc_free_grown_mb": (lines[-1]["m_free_kb"] - lines[0]["m_free_kb"]) / 1024,
        "python_mb_per_h": slope_per_hour(
            [(line["t"], line["py_alloc_b"] / 2**20) for line in lines]
        ),
        "free_lists_kb": lines[-1]["fl_b"] / 1024,
        "free_lists_grown_kb": (lines[-1]["fl_b"] - lines[0]["fl_b"]) / 1024,
    }


async def run() -> dict[str, Any]:
    figures: dict[str, Any] = {}
    for name, navcam in (("idle", False), ("navcam_30fps", True)):
        for key, value in (await rss_growth(navcam=navcam)).items():
            figures[f"memory_{name}_{key}"] = round(value, 2)
    return {
        **figures,
        "memory_method": (
            f"--sim platform, 1 station, override + 10 Hz teleop, telemetry; RSS every "
            f"{INTERVAL_S:g} s, least-squares slope over {MEASURE_S:g} s after {WARMUP_S:g} s "
            "of warm-up (start-up: session, streams, first GPS fix), extrapolated to an hour, "
            "and the growth over those seconds; python_mb_per_h: pymalloc's bytes in use, "
            "free_lists_kb: what CPython's free lists hold (capped; they were what grew). "
            "Longer: BENCH_MEMORY_SECONDS, BENCH_MEMORY_WARMUP_S"
        ),
        "memory_target_mb_per_h": 1.0,
    }
