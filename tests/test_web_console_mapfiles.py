"""The console's map and route files (web/mapfiles.js) in a real headless Chromium against a
--sim platform: a KML map and a QGC .plan route imported, a mission we cannot fly refused with
its commands named, the route exported as .waypoints (read by the station's Python readers)."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from support.console import sim_platform

from brasidas.mapfiles.files import read_route
from platformd.app import PlatformDaemon
from stationd.daemon import StationDaemon

Factory = Callable[..., Awaitable[PlatformDaemon]]
DATA = Path(__file__).parent / "data" / "mapfiles"


async def test_console_imports_and_exports_map_and_route_files(
    station: StationDaemon,
    platform_factory: Factory,
    fleet_key: bytes,
    tmp_path: Path,
    browser: Any,
) -> None:
    from playwright.async_api import expect

    await sim_platform(
        platform_factory,
        fleet_key,
        station,
        "file-rover",
        23.6530,
        f"map.file={tmp_path / 'map.geojson'}",
        f"autonomy.route_file={tmp_path / 'route.json'}",
    )
    base = f"http://127.0.0.1:{station.api_port}"
    page = await browser.new_page(viewport={"width": 1280, "height": 860})
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    await page.goto(base + "/")
    row = page.locator('#platforms tr[data-platform="file-rover"]')
    await expect(row).to_be_visible(timeout=10_000)
    await page.locator("#map .platform-icon", has_text="file-rover").click()
    await page.get_by_text("map files and background").click()  # folded at first
    tools = page.get_by_role("group", name="map and route files")
    await expect(tools).to_be_visible(timeout=15_000)
    answer = page.locator("#mapfile-answer")

    # A KML map: which placemark is the boundary and which the keep-out, as in the CLI.
    await page.get_by_label("map or route file").set_input_files(str(DATA / "field.kml"))
    await page.get_by_label("boundary selector").fill("field")
    await page.get_by_label("keep-outs selector").fill("barn")
    await page.get_by_role("button", name="import map file").click()
    await expect(answer).to_contain_text(
        "map field.kml loaded (KML): 1 keep-outs, 1 named points", timeout=15_000
    )
    area = await station.ctx.api.call_local("map_get", platform_id="file-rover")
    assert area["map"]["name"] == "field"
    await expect(page.locator("#keepouts li[data-keepout='barn']")).to_have_count(1, timeout=10_000)

    # A QGC plan's mission: home left out, closed by its DO_JUMP; shown on the map.
    await page.get_by_label("map or route file").set_input_files(str(DATA / "field.plan"))
    await page.get_by_role("button", name="import route file").click()
    await expect(answer).to_contain_text(
        "route field.plan set (QGC plan): 5 waypoints, closed", timeout=15_000
    )
    await expect(answer).to_contain_text("planned home")
    area = await station.ctx.api.call_local("map_get", platform_id="file-rover")
    assert len(area["route"]) == 5
    assert area["closed"] is True
    await expect(page.locator("#map path.route-line")).to_have_count(1, timeout=10_000)

    # Commands a ground robot cannot fly: refused, named; the route stays.
    await page.get_by_label("map or route file").set_input_files(str(DATA / "takeoff.waypoints"))
    await page.get_by_role("button", name="import route file").click()
    await expect(answer).to_contain_text("MAV_CMD_NAV_TAKEOFF (22)", timeout=15_000)
    await expect(answer).to_have_class("muted refused")
    area = await station.ctx.api.call_local("map_get", platform_id="file-rover")
    assert len(area["route"]) == 5

    # Exported as .waypoints: row 0 home, then the route as the platform has it.
    async with page.expect_download(timeout=15_000) as download_info:
        await page.get_by_role("button", name="export route as waypoints").click()
    download = await download_info.value
    assert download.suggested_filename == "file-rover.waypoints"
    text = await asyncio.to_thread(Path(await download.path()).read_text)
    assert text.startswith("QGC WPL 110\n")
    again = read_route(text, "file-rover.waypoints")
    assert [(w["lat"], w["lon"]) for w in again.waypoints] == [
        (w["lat"], w["lon"]) for w in area["route"]
    ]
    await expect(answer).to_contain_text("5 waypoints exported")
    assert errors == []
