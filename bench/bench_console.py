"""The browser console (issues 11, 20): NavCam glass-to-glass in headless Chromium (split into
capture → station and station → drawn), the station daemon's CPU while pages watch, the page's
own main-thread time with every panel open (plots, map files, every value on the values bar) in
the normal layout and in the full view with its drawer open, page open → first frame, and last
frame → STALE shown (the stream paused on the platform, the mark timed in the page).

A ``--sim`` platform (640x480 at 30 fps, x264, moving SMPTE bars) and a station daemon run as
processes; Debian's Chromium (headless, software decoding) opens the console with
``?platform=ID``. Latency is capture stamp (platform wall clock) → frame drawn on the page's
canvas (page wall clock, corrected by the station's clock offset): one host, one clock. Each
frame's stages are timed too (``glass_to_glass_stages_p50_p95_ms``: capture → station, station →
page, page → worker, decode, draw; and, outside the total, drawn → next display frame), with
the station's own share of the relay. ``--rows g2g`` measures only glass-to-glass (two windows
of ``--seconds N``, 10 by default): ``python -m bench console --rows g2g --seconds 20``.
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
SHORT = os.environ.get("BRASIDAS_BENCH_SHORT") == "1"
"""A short run (a loaded shared machine): 4 s windows and 6 stale rounds a rate."""
ROWS = {row for row in os.environ.get("BENCH_ROWS", "").split(",") if row}
G2G_ONLY = ROWS == {"g2g"}
"""``--rows g2g``: only glass-to-glass and its stages (a quicker check of that figure)."""
WINDOW_S = float(os.environ.get("BENCH_SECONDS") or (4.0 if SHORT else 10.0))
"""Each measuring window (``--seconds N``); glass-to-glass is measured over two of them."""
STALE_ROUNDS = 6 if SHORT else 12


def _quantile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return round(ordered[min(len(ordered) - 1, int(q * len(ordered)))], 2)


STAGES = ("network", "relay", "handoff", "decode", "draw", "present")
"""A frame's way (web/video-worker.js ``stages``): capture → station (the platform's encode and
send, the station's receive and depayload), station → page (the station's relay, the WebSocket;
the page's main thread until the video worker's own socket carries the frames), page → worker,
decode, draw; then, not part of glass-to-glass, drawn → the worker's next display frame (when
the compositor takes the canvas)."""


def _stages(frames: list[dict[str, float]]) -> dict[str, list[float]]:
    """Each stage's [p50, p95] (ms) over ``frames``; the p95s do not add up to the total's."""
    return {
        stage: [_quantile(values, 0.5), _quantile(values, 0.95)]
        for stage in STAGES
        if (values := [float(frame[stage]) for frame in frames if frame.get(stage) is not None])
    }


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


async def _open_every_panel(page: Any) -> None:
    """Every plot ticked, the map files open, every value on the values bar."""
    for box in await page.query_selector_all("#plot-choices input"):
        if not await box.is_checked():
            await box.check()
    await page.evaluate("document.getElementById('map-files').open = true")
    await page.click("#values-choose")
    for box in await page.query_selector_all("#values-choices input"):
        if not await box.is_checked():
            await box.check()
    await page.click("#values-choose")


async def _cpu_window(pid: int, seconds: float) -> float:
    before, started = cpu_seconds(pid), time.monotonic()
    await asyncio.sleep(seconds)
    return round((cpu_seconds(pid) - before) / (time.monotonic() - started) * 100, 1)


async def _rpc(http: aiohttp.ClientSession, base: str, method: str, **params: Any) -> Any:
    async with http.post(
        base + "/api/rpc", json={"jsonrpc": "2.0", "id": 1, "method": method, "params": params}
    ) as response:
        return (await response.json()).get("result")


async def _main_thread_ms_per_s(page: Any, seconds: float) -> dict[str, float]:
    """The page's main-thread time per second over ``seconds`` (Chrome's TaskDuration), and its
    script, layout and style parts: wall time of its tasks, so a loaded machine inflates it.
    LayoutCount: the layouts themselves (a count, per second; issue 32's declutter made ~100)."""
    cdp = await page.context.new_cdp_session(page)
    await cdp.send("Performance.enable")
    names = (
        "TaskDuration",
        "ScriptDuration",
        "LayoutDuration",
        "RecalcStyleDuration",
        "LayoutCount",
    )

    async def sample() -> dict[str, float]:
        metrics = (await cdp.send("Performance.getMetrics"))["metrics"]
        return {m["name"]: float(m["value"]) for m in metrics if m["name"] in names}

    before, started = await sample(), time.monotonic()
    await asyncio.sleep(seconds)
    after, elapsed = await sample(), time.monotonic() - started
    return {
        name: round(
            (after[name] - before[name]) / elapsed * (1 if name == "LayoutCount" else 1000), 1
        )
        for name in names
    }


async def _stale_delays(
    page: Any, http: aiohttp.ClientSession, base: str, rounds: int
) -> list[float]:
    """Pause the NavCam on the platform ``rounds`` times: last frame drawn → STALE shown (ms)."""
    delays: list[float] = []
    for _ in range(rounds):
        marks = len(await page.evaluate("window.navcam.staleMarks()"))
        await _rpc(http, base, "stream_pause", platform_id=PLATFORM_ID, stream="navcam")
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            found = await page.evaluate("window.navcam.staleMarks()")
            if len(found) > marks:
                drawn, shown = found[-1]
                delays.append(float(shown) - float(drawn))
                break
            await asyncio.sleep(0.05)
        await page.click("#video-resume")
        decoded = (await page.evaluate("window.navcam.stats()") or {}).get("decoded", 0)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            await asyncio.sleep(0.1)
            stats = await page.evaluate("window.navcam.stats()") or {}
            if stats.get("decoded", 0) > decoded + 15:
                break
    return delays


async def _glass_to_glass(page: Any) -> dict[str, Any]:
    """Glass-to-glass and its stages over two windows, every panel open: the normal layout, then
    the full view with its drawer open; the page's main-thread time in each."""
    await page.evaluate("window.navcam.keepLatencies(true)")
    main_thread = await _main_thread_ms_per_s(page, WINDOW_S - 0.5)
    # The full view with its panels drawer open: the same page, other layout.
    await page.click("#full-view")
    await page.click("#panels")
    await asyncio.sleep(1.0)
    main_thread_full = await _main_thread_ms_per_s(page, WINDOW_S - 0.5)
    await page.click("#panels")
    await page.click("#full-view")
    frames = (await page.evaluate("window.navcam.dump()"))["latencies"]
    relayed = await page.evaluate("window.navcam.relayed()") or {}
    await page.evaluate("window.navcam.keepLatencies(false)")
    latencies = [float(frame["total"]) for frame in frames]
    network = [float(frame["network"]) for frame in frames]
    page_part = [float(frame["total"]) - float(frame["network"]) for frame in frames]
    return {
        "glass_to_glass_p50_ms": _quantile(latencies, 0.5),
        "glass_to_glass_p95_ms": _quantile(latencies, 0.95),
        "glass_to_glass_max_ms": round(max(latencies), 2),
        "glass_to_glass_frames": len(latencies),
        "capture_to_station_p50_ms": _quantile(network, 0.5),
        "capture_to_station_p95_ms": _quantile(network, 0.95),
        # The rest: the station's relay, the page's receive, decode and draw.
        "station_to_drawn_p50_ms": _quantile(page_part, 0.5),
        "station_to_drawn_p95_ms": _quantile(page_part, 0.95),
        "glass_to_glass_stages_p50_p95_ms": _stages(frames),
        "glass_to_glass_target_p95_ms": 12,
        # The relay's share in the station: arrival → written to the page's socket (the
        # station's last 300 frames; the rest of "relay" is the socket and the browser).
        "station_arrival_to_written_p50_p95_ms": [
            relayed.get("relay_p50_ms"),
            relayed.get("relay_p95_ms"),
        ],
        "page_main_thread_ms_per_s_every_panel_open": main_thread["TaskDuration"],
        "page_main_thread_parts_ms_per_s": {
            "script": main_thread["ScriptDuration"],
            "layout": main_thread["LayoutDuration"],
            "style": main_thread["RecalcStyleDuration"],
        },
        "page_layouts_per_s_every_panel_open": main_thread["LayoutCount"],
        "page_main_thread_ms_per_s_full_view_panels_open": main_thread_full["TaskDuration"],
        "page_main_thread_parts_ms_per_s_full_view": {
            "script": main_thread_full["ScriptDuration"],
            "layout": main_thread_full["LayoutDuration"],
            "style": main_thread_full["RecalcStyleDuration"],
        },
        "page_layouts_per_s_full_view_panels_open": main_thread_full["LayoutCount"],
    }


async def _stale_and_pages(
    browser: Any, first: Any, base: str, url: str, station_pid: int
) -> dict[str, Any]:
    """The microphone's latency, STALE at 30 and 5 fps, a second and third page (first frame
    with the platform already streaming, the station's CPU with 3 pages)."""
    await first.click("#listen")  # the platform's microphone, decoded in the page
    audio_ms: list[float] = []
    for _ in range(30):
        await asyncio.sleep(0.2)
        figure = (await first.evaluate("window.navcam.audio()"))["latencyMs"]
        if figure is not None:
            audio_ms.append(float(figure))
    async with aiohttp.ClientSession() as http:
        stale_ms = await _stale_delays(first, http, base, STALE_ROUNDS)
        # Every patrol streams at 5 fps: the mark must follow that interval too.
        await _set_framerate(http, base, 5)
        await asyncio.sleep(3.0)
        stale_5fps_ms = await _stale_delays(first, http, base, STALE_ROUNDS)
        fps_after = (await first.evaluate("window.navcam.stats()") or {}).get("fps")
        await _set_framerate(http, base, 30)
        await asyncio.sleep(2.0)
    second, warm_ms = await _open_page(browser, url)  # the platform streams
    marks = await second.evaluate("window.navcam.marks()")
    third, _ = await _open_page(browser, url)
    await asyncio.sleep(2.0)
    three_cpu = await _cpu_window(station_pid, WINDOW_S)
    stats = await third.evaluate("window.navcam.stats()")
    for page in (second, third):
        await page.close()
    return {
        "audio_arrival_to_output_p50_ms": _quantile(audio_ms, 0.5) if audio_ms else None,
        "last_frame_to_stale_p50_ms": _quantile(stale_ms, 0.5) if stale_ms else None,
        "last_frame_to_stale_p95_ms": _quantile(stale_ms, 0.95) if stale_ms else None,
        "last_frame_to_stale_rounds": len(stale_ms),
        "last_frame_to_stale_target_p95_ms": 500,
        "last_frame_to_stale_5fps_p50_ms": _quantile(stale_5fps_ms, 0.5) if stale_5fps_ms else None,
        "last_frame_to_stale_5fps_p95_ms": _quantile(stale_5fps_ms, 0.95)
        if stale_5fps_ms
        else None,
        "last_frame_to_stale_5fps_rounds": len(stale_5fps_ms),
        "fps_during_5fps_rounds": fps_after,
        "station_cpu_pct_one_core_3_pages": three_cpu,
        "station_cpu_target_pct": "1 page < 10, 3 pages < 15",
        "page_open_to_first_frame_ms_streaming": round(warm_ms, 1),
        "first_frame_target_ms": 1000,
        "first_frame_steps_ms": {k: round(float(v), 1) for k, v in marks.items()},
        "third_page_fps": stats.get("fps"),
    }


async def _set_framerate(http: aiohttp.ClientSession, base: str, fps: int) -> None:
    await _rpc(
        http, base, "command", platform_id=PLATFORM_ID, group=10, command=5, payload=f"navcam={fps}"
    )


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
    figures: dict[str, Any] = {}
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
        if not G2G_ONLY:
            figures["station_cpu_pct_one_core_no_page"] = await _cpu_window(station.pid, 5.0)
        url = f"{base}/?platform={PLATFORM_ID}"
        async with async_playwright() as playwright:
            browser = await playwright.chromium.launch(
                executable_path=CHROMIUM, args=["--no-sandbox", "--disable-gpu"]
            )
            try:
                first, cold_ms = await _open_page(browser, url)  # starts the feed
                figures["page_open_to_first_frame_ms_cold_feed"] = round(cold_ms, 1)
                await _open_every_panel(first)
                await asyncio.sleep(2.0)
                one_cpu_task = asyncio.ensure_future(_cpu_window(station.pid, WINDOW_S))
                figures.update(await _glass_to_glass(first))
                figures["station_cpu_pct_one_core_1_page"] = await one_cpu_task
                if not G2G_ONLY:
                    figures.update(await _stale_and_pages(browser, first, base, url, station.pid))
                await first.close()
            finally:
                await browser.close()
    finally:
        for process in (station, platform):
            if process is not None and process.returncode is None:
                process.terminate()
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(process.wait(), 10)
    figures["load_average_1min"] = os.getloadavg()[0]
    figures["cpus"] = os.cpu_count()
    return figures
