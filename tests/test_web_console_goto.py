"""Click on the map to go there (issue 31, second wave), in headless Chromium against a --sim
platform: the controller presses *go to*, clicks a point, slides to confirm, and the platform
drives there through its planner (the route kept); a point outside the map is refused in the
platform's words; an observer's button is disabled saying who holds control. And the same
through ``brasidas-station goto ID LAT,LON``."""

from __future__ import annotations

import asyncio
import math
import re
from typing import Any

import pytest
from conftest import until_armable
from support.cli import run_cli
from support.console import Factory, console, rover, screenshots

from stationd.client import PlatformConnection
from stationd.daemon import StationDaemon


async def click_map_at(page: Any, lat: float, lon: float) -> None:
    box = await page.locator("#map").bounding_box()
    assert box is not None
    at = await page.evaluate(f"window.navcam.mapPixel({lat}, {lon})")
    await page.mouse.click(box["x"] + at["x"], box["y"] + at["y"])


def metres(a: tuple[float, float], b: tuple[float, float]) -> float:
    north = (a[0] - b[0]) * 111_320
    east = (a[1] - b[1]) * 111_320 * math.cos(math.radians(a[0]))
    return math.hypot(north, east)


async def test_click_on_the_map_slide_and_the_platform_goes_there(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, browser: Any
) -> None:
    from playwright.async_api import expect

    platform = await rover(
        platform_factory,
        fleet_key,
        station,
        "signaling.session_timeout=60",
        "failsafe.release_after=60",
    )
    page = await console(browser, station, "web-rover")
    await expect(page.locator("#map path.route-line")).to_have_count(1, timeout=15_000)
    shown = await station.ctx.api.call_local("map_get", platform_id="web-rover")
    route = [(w["lat"], w["lon"]) for w in shown["route"]]
    ne = route[2]  # the demo loop's far corner, past the shed
    goto = page.get_by_role("button", name="go to a point")
    await expect(goto).to_be_enabled()
    await until_armable(platform.ctx)  # (a go-to arms through the pre-arm checks)
    # A click on the map without *go to* pressed sends nothing; with it, a flag and a slider.
    await goto.click()
    await expect(goto).to_have_attribute("aria-pressed", "true")
    await click_map_at(page, *ne)
    slider = page.get_by_label(re.compile("^slide to go to "))
    await expect(slider).to_be_visible()
    await expect(page.locator("#map .goto-target")).to_have_count(1)
    await screenshots(page, "console-goto")
    await slider.fill("40")  # let go half-way: nothing goes
    # A go-to sent takes the slider and the flag away at once (before its call is answered):
    # both still up means none was sent (a pause, then the patrol's state, passed whenever
    # the call was slower than the pause).
    await expect(slider).to_have_value("0")
    await expect(slider).to_be_visible()
    await expect(page.locator("#map .goto-target")).to_have_count(1)
    assert (await station.ctx.api.call_local("patrol_get", platform_id="web-rover"))[
        "state"
    ] != "patrolling"
    await slider.fill("100")
    answer = page.locator("#patrol-answer")
    await expect(answer).to_contain_text("going to", timeout=10_000)
    await expect(page.locator("#map .goto-target")).to_have_count(0)
    report = await station.ctx.api.call_local("patrol_get", platform_id="web-rover")
    assert report["state"] == "patrolling", report
    assert report["waypoints"] == 1, report
    going = await station.ctx.api.call_local("map_get", platform_id="web-rover")
    (target,) = going["route"]
    assert metres((target["lat"], target["lon"]), ne) < 1.0  # where the click was
    assert platform.ctx.patrol is not None
    assert platform.ctx.patrol.detour == "go to"
    await expect(page.locator("#patrol-state")).to_have_attribute(
        "data-state", "patrolling", timeout=10_000
    )

    # A point outside the map: the platform's reason, nothing moves elsewhere.
    await goto.click()
    outside = (ne[0] + 20 / 110_574, ne[1])  # 10 m north of the field's boundary
    box = await page.locator("#map").bounding_box()
    assert box is not None
    await page.mouse.move(box["x"] + box["width"] / 2, box["y"] + box["height"] / 2)
    await page.mouse.wheel(0, 400)  # zoomed out: the point is in sight
    await page.wait_for_timeout(500)
    await click_map_at(page, *outside)
    await page.get_by_label(re.compile("^slide to go to ")).fill("100")
    await expect(answer).to_contain_text("go to refused", timeout=10_000)
    await expect(answer).to_have_class(re.compile("refused"))

    # Another station takes control: the button is disabled, saying who holds it.
    intruder = PlatformConnection(
        "web-rover", platform.ctx.signaling_url, station_id="intruder", fleet_key=fleet_key
    )
    await intruder.open()
    try:
        taken = await intruder.call(
            "issue_system_command", group=10, command=0, payload="state=True,force=yes"
        )
        assert taken["accepted"], taken
        await expect(goto).to_be_disabled(timeout=15_000)
        await expect(goto).to_have_attribute("title", re.compile("^intruder holds control"))
    finally:
        await intruder.close()


async def test_the_goto_command_drives_there_and_says_why_not(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes
) -> None:
    platform = await rover(platform_factory, fleet_key, station)
    url = platform.ctx.signaling_url
    assert (await run_cli(station, "connect", "web-rover", "--url", url))[0] == 0
    # The pre-arm checks (a fix, the simulated controller answering: seconds on a loaded
    # machine) first: a go-to arms through them, and is refused before.
    await until_armable(platform.ctx)
    shown = await station.ctx.api.call_local("map_get", platform_id="web-rover")
    lat, lon = shown["route"][1]["lat"], shown["route"][1]["lon"]
    code, out, err = await run_cli(station, "goto", "web-rover", f"{lat},{lon}")
    assert code == 0, err
    assert out.startswith(f"going to {lat:.7f}, {lon:.7f}"), out
    assert "waypoint   1 of 1" in out, out
    assert platform.ctx.patrol is not None
    assert platform.ctx.patrol.detour == "go to"
    code, out, err = await run_cli(station, "goto", "web-rover", f"{lat + 0.01},{lon}")
    assert code != 0, (out, err)
    assert "go to refused" in err, (out, err)
    code, out, err = await run_cli(station, "goto", "web-rover", "north")
    assert code != 0, (out, err)
    assert "LAT,LON" in err, (out, err)
    # patrol start goes back to the route
    code, out, err = await run_cli(station, "patrol", "web-rover", "start")
    assert code == 0, err
    assert platform.ctx.patrol.detour is None
    assert (await station.ctx.api.call_local("patrol_get", platform_id="web-rover"))[
        "waypoints"
    ] == len(shown["route"])


def bearing(a: tuple[float, float], b: tuple[float, float]) -> float:
    north = (b[0] - a[0]) * 111_320
    east = (b[1] - a[1]) * 111_320 * math.cos(math.radians(a[0]))
    return math.degrees(math.atan2(east, north)) % 360


async def test_home_is_in_telemetry_on_the_map_and_in_the_toolbar(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, browser: Any
) -> None:
    """Home is the first fix until the route brings its own (a mission file's); the map marks
    it and the toolbar says how far and which way it is from the platform."""
    from playwright.async_api import expect

    await rover(platform_factory, fleet_key, station)
    page = await console(browser, station, "web-rover")
    home_pill = page.get_by_label("home", exact=True)
    await expect(home_pill).to_have_text(re.compile(r"^⌂ \d+ m \d+°$"), timeout=15_000)
    report = await station.ctx.api.call_local("get_telemetry", platform_id="web-rover")
    first_fix = report["snapshot"]["autonomy"]["home"]
    assert len(first_fix) == 2, report["snapshot"]["autonomy"]
    await expect(page.locator("#map .map-flag.home")).to_have_count(1)

    # A route with a home 30 m south-west of the first fix: that is home now.
    home = (first_fix[0] - 21 / 110_574, first_fix[1] - 21 / (111_320 * math.cos(0.6622)))
    connection = await station.ctx.connection("web-rover")
    shown = await station.ctx.api.call_local("map_get", platform_id="web-rover")
    await connection.call(
        "set_waypoints", waypoints=[[w["lat"], w["lon"]] for w in shown["route"]], home=list(home)
    )
    loop = asyncio.get_running_loop()
    deadline = loop.time() + 10
    while True:
        snapshot = (await station.ctx.api.call_local("get_telemetry", platform_id="web-rover"))[
            "snapshot"
        ]
        if snapshot["autonomy"]["home"] == pytest.approx(list(home), abs=1e-7):
            break
        assert loop.time() < deadline, snapshot["autonomy"]
        await asyncio.sleep(0.1)
    here = (snapshot["pose"]["lat"], snapshot["pose"]["lon"])
    away, towards = metres(here, home), bearing(here, home)
    assert 25 < away < 35, (away, towards)
    assert 200 < towards < 250, (away, towards)
    await expect(home_pill).to_have_text(re.compile(r"^⌂ (2[5-9]|3[0-5]) m 2[0-4]\d°$"))
    shown_m = float(await home_pill.get_attribute("data-metres") or "nan")
    assert shown_m == pytest.approx(away, abs=2.0)
    await screenshots(page, "console-home")
