"""The console's values bar, full view and grid labels (issue 31) in headless Chromium against a
--sim platform: the operator picks the values shown and the choice survives a reload; the full
view fills the screen with the instruments over the main view at 1366x768 and 1920x1080, with
nothing off screen; the map's grid labels keep off the waypoint numbers."""

from __future__ import annotations

import re
from typing import Any

from support.console import SETTLED_JS, Factory, console, frames_decoded, rover, screenshots

from stationd.daemon import StationDaemon

SIZES = ((1366, 768), (1920, 1080))
Box = dict[str, float]


def overlap(a: Box, b: Box) -> bool:
    return (
        a["x"] < b["x"] + b["width"]
        and b["x"] < a["x"] + a["width"]
        and a["y"] < b["y"] + b["height"]
        and b["y"] < a["y"] + a["height"]
    )


def inside(inner: Box, outer: Box, slack: float = 1.0) -> bool:
    return (
        inner["x"] >= outer["x"] - slack
        and inner["y"] >= outer["y"] - slack
        and inner["x"] + inner["width"] <= outer["x"] + outer["width"] + slack
        and inner["y"] + inner["height"] <= outer["y"] + outer["height"] + slack
    )


async def box_of(page: Any, selector: str) -> Box:
    found = await page.locator(selector).bounding_box()
    assert found is not None, f"{selector} is not drawn"
    return dict(found)


async def test_the_operator_chooses_the_values_and_the_choice_is_kept(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, browser: Any
) -> None:
    """The values bar shows the default figures read from telemetry (km/h, satellites, volts,
    the link's round trip, glass-to-glass); unticking one and ticking another changes the bar,
    and a reload keeps the choice. In map main the bar moves onto the map."""
    from playwright.async_api import expect

    await rover(platform_factory, fleet_key, station)
    page = await console(browser, station, "web-rover")
    await frames_decoded(page, at_least=5)
    bar = page.get_by_role("group", name="values")
    await expect(bar).to_be_visible(timeout=10_000)
    await expect(page.locator("#video-box > #values-bar")).to_have_count(1)
    keys = {"speed": "speed", "GPS sats": "sats", "battery": "volts", "link RTT": "rtt"}
    keys |= {"glass-to-glass": "latency", "heading": "heading", "CPU temp": "cpu", "roll": "roll"}
    figure = lambda name: bar.locator(f'[data-key="{keys[name]}"] .value-figure')  # noqa: E731
    await expect(figure("speed")).to_have_text(re.compile(r"^\d+\.\d km/h$"), timeout=10_000)
    await expect(figure("GPS sats")).to_have_text(re.compile(r"^\d+$"))
    await expect(figure("battery")).to_have_text(re.compile(r"^\d+\.\d V$"))
    await expect(figure("link RTT")).to_have_text(re.compile(r"^\d+ ms$"))
    await expect(figure("glass-to-glass")).to_have_text(re.compile(r"^\d+ ms$"))
    await expect(figure("heading")).to_have_text(re.compile(r"^(\d{3}°|—)$"))
    await expect(figure("CPU temp")).to_have_count(0)

    await page.get_by_role("button", name="values…").click()
    choices = page.get_by_role("dialog", name="choose values")
    await expect(choices).to_be_visible()
    await choices.get_by_label("speed", exact=True).uncheck()
    await choices.get_by_label("roll", exact=True).check()
    await page.keyboard.press("Escape")
    await expect(choices).to_be_hidden()
    await expect(figure("speed")).to_have_count(0)
    await expect(figure("roll")).to_have_count(1)

    await page.reload()
    await expect(bar).to_be_visible(timeout=10_000)
    await expect(figure("speed")).to_have_count(0)
    await expect(figure("roll")).to_have_text("—")  # the simulator reports no attitude: no 0
    await expect(figure("battery")).to_have_text(re.compile(r"^\d+\.\d V$"), timeout=10_000)
    # A picture that has gone has no glass-to-glass (the figure is not held).
    await expect(figure("glass-to-glass")).to_have_text(re.compile(r"^\d+ ms$"), timeout=15_000)
    await station.ctx.api.call_local("stream_pause", platform_id="web-rover", stream="navcam")
    await expect(figure("glass-to-glass")).to_have_text("—", timeout=5_000)
    # Map main: the bar runs along the map's top, clear of its zoom buttons.
    await page.locator("#swap-view").click()
    await expect(page.locator("#map > #values-bar")).to_have_count(1)
    zoom = await box_of(page, "#map .leaflet-control-zoom")
    assert not overlap(zoom, await box_of(page, "#values-bar"))
    await screenshots(page, "console-values-map-main")


async def test_the_full_view_fills_the_screen_with_the_instruments_over_it(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, browser: Any
) -> None:
    """F: the video fills the area under the header, the map is an inset in its lower left,
    compass, horizon and values bar lie over the picture, apart from each other and inside
    the screen at both sizes; the panels drawer brings the controls, patrol and platforms on
    screen; map main fills it with the map; a reload keeps the full view; F again goes back."""
    from playwright.async_api import expect

    await rover(platform_factory, fleet_key, station)
    page = await console(browser, station, "web-rover")
    await frames_decoded(page, at_least=5)
    await expect(page.get_by_role("button", name="manual override")).to_be_enabled(timeout=15_000)
    await page.keyboard.press("KeyF")
    await expect(page.locator("body")).to_have_class(re.compile(r"\bfull-bleed\b"))
    panels = page.get_by_role("button", name="panels")
    await expect(panels).to_be_visible()
    await expect(page.locator("#side")).to_be_hidden()
    for width, height in SIZES:
        await page.set_viewport_size({"width": width, "height": height})
        await page.evaluate(SETTLED_JS)
        screen = {"x": 0.0, "y": 0.0, "width": float(width), "height": float(height)}
        main = await box_of(page, "main")
        video = await box_of(page, "#video-box")
        assert video["width"] >= main["width"] - 2
        assert video["height"] >= main["height"] - 2
        assert main["y"] + main["height"] <= height + 1
        assert main["height"] >= height - 120
        floating = {
            name: await box_of(page, name)
            for name in ("#compass", "#horizon", "#values-bar", "#map", "#toolbar", "#stop")
        }
        for name, shown in floating.items():
            assert inside(shown, screen), (width, name, shown)
        for first in ("#compass", "#horizon", "#map"):
            assert not overlap(floating[first], floating["#values-bar"]), (width, first)
        assert not overlap(floating["#map"], await box_of(page, "#middle")), width
        assert inside(floating["#map"], video)
        assert inside(floating["#compass"], video)
    await screenshots(page, "console-full")

    await panels.click()
    await expect(page.locator("#side")).to_be_visible()
    for width, height in SIZES:
        await page.set_viewport_size({"width": width, "height": height})
        await page.evaluate(SETTLED_JS)
        screen = {"x": 0.0, "y": 0.0, "width": float(width), "height": float(height)}
        drawer = await box_of(page, "#side")
        for name in ("#override", "#streams", "#patrol-state", "#compass", "#notifications"):
            assert inside(await box_of(page, name), screen), (width, name)
        assert not overlap(await box_of(page, "#middle"), drawer), width
    await page.set_viewport_size({"width": 1366, "height": 768})
    await page.get_by_role("button", name="manual override").click()  # still works from there
    await expect(page.locator("#driving")).to_contain_text("driving web-rover", timeout=10_000)
    await screenshots(page, "console-full-panels")

    await panels.click()
    await page.keyboard.press("KeyM")
    await expect(page.locator("body")).to_have_class(re.compile(r"\bmap-main\b"))
    await page.evaluate(SETTLED_JS)
    area, main = await box_of(page, "#map"), await box_of(page, "main")
    assert area["width"] >= main["width"] - 2
    assert area["height"] >= main["height"] - 2
    inset = await box_of(page, "#video-box")
    assert inside(inset, area)
    assert inset["width"] < area["width"] / 2
    # The route is fitted beside the inset and the instruments, not under them.
    instruments = await box_of(page, "#middle")
    labels = page.locator("#map .waypoint-label")
    assert await labels.count() >= 4
    for index in range(await labels.count()):
        label = await labels.nth(index).bounding_box()
        assert label is not None, (index, label)
        assert inside(label, area), (index, label)
        assert not overlap(label, inset), (index, label)
        assert not overlap(label, instruments), (index, label)
    await screenshots(page, "console-full-map-main")

    await page.reload()  # the layout is kept for the next visit
    await expect(page.locator("body")).to_have_class(re.compile(r"\bfull-bleed\b"))
    await page.locator("#video").click()  # focus off any field
    await page.keyboard.press("KeyF")
    await expect(page.locator("body")).not_to_have_class(re.compile(r"\bfull-bleed\b"))
    await expect(page.locator("#side > #map")).to_have_count(1)
    await expect(page.locator("#video-pane > #controls")).to_have_count(1)


async def grid_clear_of_waypoints(page: Any) -> int:
    """No shown grid label covers a shown waypoint number, named point or marker; returns how
    many grid labels are shown."""
    boxes = await page.evaluate(
        """() => {
        const shown = (selector) => [...document.querySelectorAll(selector)]
          .filter((e) => !e.closest('.label-hidden') && getComputedStyle(e).visibility !== 'hidden')
          .map((e) => { const r = e.getBoundingClientRect();
                        return {x: r.left, y: r.top, width: r.width, height: r.height, text: e.textContent}; })
          .filter((r) => r.width > 0);
        const map = document.getElementById('map').getBoundingClientRect();
        const inMap = (r) => r.x >= map.left && r.x + r.width <= map.right && r.y >= map.top && r.y + r.height <= map.bottom;
        return {grid: shown('#map .grid-label').filter(inMap),
                others: shown('#map .waypoint-label, #map .area-point-name, #map .platform-icon, #map .map-flag')};
      }"""
    )
    for label in boxes["grid"]:
        for other in boxes["others"]:
            assert not overlap(label, other), (label, other)
    return len(boxes["grid"])


async def test_grid_labels_keep_off_the_waypoint_numbers(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, browser: Any
) -> None:
    """A route whose waypoints stand where the grid writes its distances: each grid label moves
    along its line or hides, and no grid label's box overlaps a waypoint number's, at both
    sizes (it used to be drawn into the tiles, under the numbers)."""
    from playwright.async_api import expect

    await rover(platform_factory, fleet_key, station)
    page = await console(browser, station, "web-rover")
    labels = page.locator("#map .waypoint-label")
    await expect(labels).to_have_count(4, timeout=15_000)
    await page.evaluate(SETTLED_JS)
    route = (await station.ctx.api.call_local("map_get", platform_id="web-rover"))["route"]
    (lat0, lon0), (lat1, lon1) = (
        (route[0]["lat"], route[0]["lon"]),
        (
            route[2]["lat"],
            route[2]["lon"],
        ),
    )
    # The map settles its fit after the route arrives: read the grid until a label lies
    # inside the loop (the field the test lays waypoints on), for at most 10 s.
    targets: list[dict[str, Any]] = []
    grid: list[dict[str, Any]] = []
    view: dict[str, Any] = {}

    def geo(x: float, y: float) -> list[float]:
        """[lat, lon] of a page pixel (the map is linear over this field)."""
        p0, p1, map_box = view["p0"], view["p1"], view["map"]
        mx, my = x - map_box["x"], y - map_box["y"]
        lon = lon0 + (mx - p0["x"]) * (lon1 - lon0) / (p1["x"] - p0["x"])
        lat = lat0 + (my - p0["y"]) * (lat1 - lat0) / (p1["y"] - p0["y"])
        return [lat, lon]

    for attempt in range(40):
        view["p0"] = await page.evaluate(f"window.navcam.mapPixel({lat0}, {lon0})")
        view["p1"] = await page.evaluate(f"window.navcam.mapPixel({lat1}, {lon1})")
        view["map"] = await box_of(page, "#map")
        # The grid labels inside the field (the demo loop's 40 m x 30 m and a margin).
        grid = await page.evaluate(
            """() => [...document.querySelectorAll('#map .grid-label')].map((e) => {
              const r = e.getBoundingClientRect();
              return {x: r.left + r.width / 2, y: r.top + r.height / 2, spot: e.dataset.spot, text: e.textContent};
            })"""
        )
        south, north = sorted((lat0, lat1))
        west, east = sorted((lon0, lon1))
        targets = [
            label
            for label in grid
            if south <= geo(label["x"], label["y"])[0] <= north
            and west <= geo(label["x"], label["y"])[1] <= east
            and label["spot"] == "0.5"
        ]
        if targets:
            break
        if (
            attempt % 10 == 9
        ):  # the fit left no grid line inside the loop: zoom in, as an operator would
            await page.locator("#map .leaflet-control-zoom-in").click()
        await page.wait_for_timeout(250)
    assert targets, f"no grid label inside the loop: {grid}"
    # Waypoints on each label and 8 px either side of it: their numbers cover its middle.
    waypoints = []
    for label in targets[:2]:
        for dy in (-8, 0, 8):
            waypoints.append(geo(label["x"], label["y"] + dy))
    await station.ctx.api.call_local("route_set", platform_id="web-rover", waypoints=waypoints)
    sent = await station.ctx.api.call_local("patrol_get", platform_id="web-rover")
    assert sent["waypoints"] == len(waypoints), sent
    await expect(labels).to_have_count(len(waypoints), timeout=10_000)
    for width, height in SIZES:
        await page.set_viewport_size({"width": width, "height": height})
        await page.evaluate(SETTLED_JS)  # the resize's new tiles placed, not a fixed 500 ms
        assert await grid_clear_of_waypoints(page) > 0
    # The targeted labels moved along their line or hid: they did not stay under the numbers.
    moved = await page.evaluate(
        """(texts) => [...document.querySelectorAll('#map .grid-label')]
          .filter((e) => texts.includes(e.textContent))
          .map((e) => e.dataset.spot !== '0.5' || e.classList.contains('label-hidden'))""",
        [label["text"] for label in targets[:2]],
    )
    assert any(moved), moved
    await page.set_viewport_size({"width": 1366, "height": 768})
    await screenshots(page, "console-grid-labels")


# Every grid label's box made an obstacle, so that each must move along its line: the boxes the
# placement reserves (pushed onto `placed` in label order, one per label left shown) against
# where the moved labels are then drawn.
RESERVED_AND_DRAWN_JS = """async () => {
  const { placeGridLabels } = await import('/static/map.js');
  const container = document.getElementById('map');
  const labels = [...container.querySelectorAll('.grid-label')];
  const placed = labels.map((label) => label.getBoundingClientRect());
  const before = placed.length;
  placeGridLabels(container, placed);
  const shown = labels.filter((label) => !label.classList.contains('label-hidden'));
  return placed.slice(before).map((box, index) => {
    const drawn = shown[index].getBoundingClientRect();
    return { text: shown[index].textContent, spot: shown[index].dataset.spot,
             reserved: [box.left, box.top, box.right, box.bottom],
             drawn: [drawn.left, drawn.top, drawn.right, drawn.bottom] };
  });
}"""


async def test_a_grid_label_is_drawn_where_its_room_was_measured(
    station: StationDaemon, browser: Any
) -> None:
    """A grid label moved along its line is drawn exactly in the box the declutter found free
    for it, at a whole and a half zoom step. Its spot is a fraction of the tile's edge inside
    the grid line: measured on the tile's outer box, a label moved half an edge landed half a
    pixel (zoomed in, more) beside its measured box, over a neighbour's edge."""
    page = await console(browser, station)
    # The drawn tiles' scale (1 at a whole zoom step), once the map is at a half step if asked.
    scale_js = """(half) => new Promise((done) => {
      const tile = () => document.querySelector('#map .grid-tile');
      const scale = () => tile().getBoundingClientRect().width / tile().offsetWidth;
      const zooming = () => document.querySelector('#map .leaflet-zoom-anim');
      const check = () => (!half || (Math.abs(scale() - 1) > 0.1 && !zooming()) ? done(scale()) : requestAnimationFrame(check));
      check();
    })"""
    map_box = await box_of(page, "#map")
    await page.evaluate(SETTLED_JS)
    for step in ("whole", "half"):
        if step == "half":  # a small turn of the wheel: half a step (the map snaps to 0.5)
            await page.mouse.move(map_box["x"] + 40, map_box["y"] + map_box["height"] / 2)
            await page.mouse.wheel(0, -20)
            await page.evaluate(scale_js, True)
            await page.evaluate(SETTLED_JS)
        scale = await page.evaluate(scale_js, False)
        assert (scale == 1) == (step == "whole"), (step, scale)
        moves = await page.evaluate(RESERVED_AND_DRAWN_JS)
        assert moves, f"no grid label could move at a {step} step"
        for move in moves:
            for reserved, drawn in zip(move["reserved"], move["drawn"], strict=True):
                assert abs(reserved - drawn) < 0.02, (step, scale, move)
