"""The browser console's test rig: --sim platforms beaconing to a test's station, the page
opened on it, and what the page shows of them."""

from __future__ import annotations

import asyncio
import os
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from conftest import (
    quiet_platform_config,
)

from platformd.app import PlatformDaemon
from stationd.daemon import StationDaemon

Factory = Callable[..., Awaitable[PlatformDaemon]]

FRAMES_COUNTED = "navcam.idle_framerate=15"
"""The setting of a test that waits for tens of decoded frames before the override is engaged
(30 fps): at 15 fps they come in a third of the idle 5 fps's time."""


async def sim_platform(
    factory: Factory, key: bytes, station: StationDaemon, name: str, longitude: float, *extra: str
) -> PlatformDaemon:
    config = quiet_platform_config(
        f"platform.id={name}",
        "beacon.enabled=true",
        f"beacon.port={station.config.discovery.port}",
        'beacon.destinations=["127.0.0.1"]',
        "beacon.listen=false",  # unicast: the station alone must hold the port
        "beacon.max_interval=1.0",
        "sim.enabled=true",
        f"sim.longitude={longitude}",
        "gps.enabled=true",
        "gps.sim_rate_hz=10",
        "motor.enabled=true",
        "navcam.enabled=true",
        "navcam.sim_pattern=smpte",
        "navcam.sim_motion=4",
        "audio.enabled=true",  # a test tone as the microphone
        *extra,
    )
    return await factory(config, key)


async def platforms_in_view(page: Any, timeout: float = 10.0) -> None:
    """Every platform's marker lies inside the visible map (where it can be seen and clicked),
    within ``timeout`` seconds."""
    icons = page.locator("#map .platform-icon")

    async def outside() -> list[str]:
        area = await page.locator("#map").bounding_box()
        names = []
        for index in range(await icons.count()):
            box = await icons.nth(index).bounding_box()
            if box is None or not (
                area["x"] <= box["x"] <= area["x"] + area["width"] - box["width"]
                and area["y"] <= box["y"] <= area["y"] + area["height"] - box["height"]
            ):
                names.append(await icons.nth(index).text_content())
        return names

    deadline = asyncio.get_running_loop().time() + timeout
    while missing := await outside():
        assert asyncio.get_running_loop().time() < deadline, f"outside the map: {missing}"
        await asyncio.sleep(0.1)


async def frames_decoded(page: Any, at_least: int, timeout: float = 15.0) -> int:
    """Wait until the page's Worker has decoded ``at_least`` frames (counted in the Worker;
    polled from here: the page's CSP forbids the eval that wait_for_function needs)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + timeout
    count = 0
    while loop.time() < deadline:
        count = int(await page.locator("#video").get_attribute("data-frames-decoded") or 0)
        if count >= at_least:
            return count
        await asyncio.sleep(0.1)
    raise AssertionError(f"only {count} frames decoded in {timeout} s")


DOCS = Path(__file__).resolve().parents[2] / "docs"
"""Screenshots at both screen sizes, kept current in docs/ when BRASIDAS_SCREENSHOT=1."""


SETTLED_JS = """() => new Promise((done) => {
  const frames = () => requestAnimationFrame(() => requestAnimationFrame(done));
  const wait = () => document.querySelector("#map .leaflet-zoom-anim") ? setTimeout(wait, 50) : frames();
  wait();
})"""
"""Resolves once the map's zoom animation is over (Leaflet marks its map pane, inside #map,
while it runs) and two frames more have run: the page's
resize handlers, its ResizeObservers (the map's, the plots') and what they left for the next
frame (the map's label declutter) have all run."""


async def screenshots(page: Any, name: str) -> None:
    """The page at 1366x768 and 1920x1080: it fits without scrolling (checked always), and
    with BRASIDAS_SCREENSHOT=1 its pictures go to docs/."""
    for width, height in ((1366, 768), (1920, 1080)):
        await page.set_viewport_size({"width": width, "height": height})
        # Settled, not a fixed 300 ms: 32 of those were 10 s of the browser tests' one lane.
        await page.evaluate(SETTLED_JS)
        size = await page.evaluate(
            "[document.documentElement.scrollWidth, document.documentElement.scrollHeight]"
        )
        assert size[0] <= width and size[1] <= height, f"scrolls at {width}x{height}: {size}"
        if os.environ.get("BRASIDAS_SCREENSHOT") == "1":
            await page.wait_for_timeout(300)  # a picture for the docs: any animation over
            await page.screenshot(path=str(DOCS / f"{name}-{width}x{height}.png"))
    await page.set_viewport_size({"width": 1366, "height": 768})


async def console(browser: Any, station: StationDaemon, platform_id: str = "") -> Any:
    page = await browser.new_page(viewport={"width": 1366, "height": 768})
    query = f"?platform={platform_id}" if platform_id else ""
    await page.goto(f"http://127.0.0.1:{station.api_port}/{query}")
    return page


async def rover(
    factory: Factory, key: bytes, station: StationDaemon, *extra: str
) -> PlatformDaemon:
    return await sim_platform(factory, key, station, "web-rover", 23.6530, *extra)
