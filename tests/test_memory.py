"""The platform's memory does not grow while it runs: a busy ``--sim`` platform (one station,
override engaged, 10 Hz teleop, telemetry streaming) in a child process, its Python allocations
compared across tracemalloc snapshots. A site that gains at every snapshot is a leak."""

from __future__ import annotations

import asyncio
from pathlib import Path

from bench.bench_memory import busy_platform, load_snapshot, steady_growth

WARMUP_S = 6.0
STEP_S = 5.0
SNAPSHOTS = 4
LIMIT_BYTES = 6_000
"""Steady growth allowed over the 15 s measured. The leak issue 10 found (the AX3500
simulator's record, one list entry per controller command) gains ~13 KB here; churn that
happens to grow three times in a row (file objects' buffers) ~1-3 KB."""


async def test_busy_platform_allocations_do_not_grow(tmp_path: Path) -> None:
    async with busy_platform(frames=1, interval=60.0) as probe:
        await asyncio.sleep(WARMUP_S)  # sessions, streams and caches settle
        paths = []
        for index in range(SNAPSHOTS):
            if index:
                await asyncio.sleep(STEP_S)
            paths.append(await probe.snapshot(str(tmp_path / f"{index}.snapshot")))
    grown = steady_growth([load_snapshot(path) for path in paths])
    total = sum(size for _, size in grown)
    assert total < LIMIT_BYTES, "\n".join(f"{size:+8d} B  {site}" for site, size in grown[:15])
