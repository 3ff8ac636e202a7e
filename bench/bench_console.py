"""The browser console (issue 11): NavCam glass-to-glass in headless Chromium, the station
daemon's CPU while pages watch, and page open → first frame.

A ``--sim`` platform (640x480 at 30 fps, x264, moving SMPTE bars) and a station daemon run as
processes; Debian's Chromium (headless, software decoding) opens the console with
``?platform=ID``. Latency is capture stamp (platform wall clock) → frame drawn on the page's
canvas (page wall clock, corrected by the station's clock offset): one host, one clock.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import shutil
import socket
import sys
import time
from typing import Any

import aiohttp

from bench.support import cpu_seconds, free_port, start_platform, wait_ready

PLATFORM_ID = "bench-console"
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
WINDOW_S = 10.0


def _quantile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return round(ordered[min(len(ordered) - 1, int(q * len(ordered)))], 2)


async def _start_station(api_port: int, discovery_port: int) -> asyncio.subprocess.Process:
    args = [sys.executable, "-m", "stationd", "serve"]
    for item in (
        f"station.api_port={api_port}",
        f"discovery.port={discovery_port}",
        "discovery.bind_host=127.0.0.1",
    ):
        args += ["--set", item]
    return await asyncio.create_subprocess_exec(
        *args, stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL
    )


async def _open_page(browser: Any, url: str) -> tuple[Any, float]:
    """A new page watching the platform; returns it and its open → first frame time (ms)."""
    page = await browser.new_page()
    await page.goto(url)
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        stats = await page.evaluate("window.navcam.stats()")
        if stats and stats.get("firstDrawMs"):
            origin = await page.evaluate("performance.timeOrigin")
            return page, float(stats["firstDrawMs"]) - float(origin)
        await asyncio.sleep(0.05)
    raise TimeoutError("no frame drawn in 20 s")


async def _cpu_window(pid: int, seconds: float) -> float:
    before, started = cpu_seconds(pid), time.monotonic()
    await asyncio.sleep(seconds)
    return round((cpu_seconds(pid) - before) / (time.monotonic() - started) * 100, 1)


async def run() -> dict[str, Any]:
    from playwright.async_api import async_playwright

    api_port, discovery_port = free_port(), free_port(socket.SOCK_DGRAM)
    signaling_port = free_port()
    platform = await start_platform(
        f"platform.id={PLATFORM_ID}",
        f"signaling.port={signaling_port}",
        f"beacon.port={discovery_port}",
        'beacon.destinations=["127.0.0.1"]',
        "beacon.listen=false",
        "beacon.max_interval=1.0",
        "navcam.idle_framerate=30",
        "navcam.sim_pattern=smpte",
        "navcam.sim_motion=4",
        "audio.enabled=true",
    )
    station: asyncio.subprocess.Process | None = None
    try:
        await wait_ready(signaling_port)
        station = await _start_station(api_port, discovery_port)
        await wait_ready(api_port)
        base = f"http://127.0.0.1:{api_port}"
        async with aiohttp.ClientSession() as http:
            for _ in range(100):  # until the station has heard the platform's beacon
                async with http.post(
                    base + "/api/rpc",
                    json={"jsonrpc": "2.0", "id": 1, "method": "list_platforms"},
                ) as response:
                    if any(p["id"] == PLATFORM_ID for p in (await response.json())["result"]):
                        break
                await asyncio.sleep(0.1)
        idle_cpu = await _cpu_window(station.pid, 5.0)
        url = f"{base}/?platform={PLATFORM_ID}"
        async with async_playwright() as playwright:
            browser = await playwright.chromium.launch(
                executable_path=CHROMIUM, args=["--no-sandbox", "--disable-gpu"]
            )
            try:
                first, cold_ms = await _open_page(browser, url)  # starts the feed
                await asyncio.sleep(2.0)
                await first.evaluate("window.navcam.keepLatencies(true)")
                one_cpu = await _cpu_window(station.pid, WINDOW_S)
                dump = await first.evaluate("window.navcam.dump()")
                latencies = [float(total) for total, _ in dump["latencies"]]
                network = [float(part) for _, part in dump["latencies"]]
                await first.click("#listen")  # the platform's microphone, decoded in the page
                audio_ms: list[float] = []
                for _ in range(30):
                    await asyncio.sleep(0.2)
                    figure = (await first.evaluate("window.navcam.audio()"))["latencyMs"]
                    if figure is not None:
                        audio_ms.append(float(figure))
                second, warm_ms = await _open_page(browser, url)  # the platform streams
                marks = await second.evaluate("window.navcam.marks()")
                third, _ = await _open_page(browser, url)
                await asyncio.sleep(2.0)
                three_cpu = await _cpu_window(station.pid, WINDOW_S)
                stats = await third.evaluate("window.navcam.stats()")
                for page in (first, second, third):
                    await page.close()
            finally:
                await browser.close()
    finally:
        for process in (station, platform):
            if process is not None and process.returncode is None:
                process.terminate()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(process.wait(), 10)
    return {
        "glass_to_glass_p50_ms": _quantile(latencies, 0.5),
        "glass_to_glass_p95_ms": _quantile(latencies, 0.95),
        "glass_to_glass_max_ms": round(max(latencies), 2),
        "glass_to_glass_frames": len(latencies),
        "capture_to_station_p50_ms": _quantile(network, 0.5),
        "capture_to_station_p95_ms": _quantile(network, 0.95),
        "glass_to_glass_target_p95_ms": 25,
        "audio_arrival_to_output_p50_ms": _quantile(audio_ms, 0.5) if audio_ms else None,
        "station_cpu_pct_one_core_no_page": idle_cpu,
        "station_cpu_pct_one_core_1_page": one_cpu,
        "station_cpu_pct_one_core_3_pages": three_cpu,
        "station_cpu_target_pct": "1 page < 10, 3 pages < 15",
        "page_open_to_first_frame_ms_streaming": round(warm_ms, 1),
        "page_open_to_first_frame_ms_cold_feed": round(cold_ms, 1),
        "first_frame_target_ms": 1000,
        "first_frame_steps_ms": {k: round(float(v), 1) for k, v in marks.items()},
        "load_average_1min": os.getloadavg()[0],
        "third_page_fps": stats.get("fps"),
        "cpus": os.cpu_count(),
    }
