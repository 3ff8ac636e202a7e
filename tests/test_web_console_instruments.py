"""The console's instruments and views (issue 20) in a real headless Chromium against --sim
platforms: the instrument panel (speed, heading as the CLI's course, roll/pitch, battery with
time left, link quality, the speed cap and its reason as text, the stick, the driving hint and
why nothing moves), plots receiving points, the map/video swap and its scale bar, map labels
that never cover each other, notifications kept across a reload (bursts counted, cleared
said), and an answer line that speaks a sentence and expires.

One station, one browser page for all of it (each launch costs seconds here). The page's
clock is Playwright's (page.clock): the test steps it where the page counts time."""

from __future__ import annotations

import re
import time
from typing import Any

from conftest import wait_until
from support.cli import run_cli
from support.console import (
    SETTLED_JS,
    Factory,
    frames_decoded,
    rover,
    screenshots,
    sim_platform,
)

from brasidas import topics
from brasidas.annunciator import LINK_LOST
from brasidas.messages import StationNotification
from platformd.app import PlatformDaemon
from stationd.daemon import StationDaemon

HEADING_DEG = 200.0
"""The simulated rover's compass heading at start: the page says the CLI's number."""

OVERLAP_JS = """
() => {
  // Every map label shown (platform names, named points, waypoint numbers), its drawn box.
  const shown = [...document.querySelectorAll("#map .platform-icon span, #map .area-point-name, #map .waypoint-label")]
    .filter((e) => !e.classList.contains("label-hidden") && getComputedStyle(e).visibility !== "hidden")
    .map((e) => ({ text: e.textContent, box: e.getBoundingClientRect().toJSON() }));
  const overlaps = [];
  for (let i = 0; i < shown.length; i++) for (let j = i + 1; j < shown.length; j++) {
    const a = shown[i].box, b = shown[j].box;
    if (a.left < b.right && b.left < a.right && a.top < b.bottom && b.top < a.bottom) overlaps.push([shown[i].text, shown[j].text]);
  }
  return { shown: shown.map((s) => s.text), overlaps };
}
"""


async def cli_heading(station: StationDaemon) -> int | None:
    """The heading `brasidas-station status web-rover` prints on its pose line (None: it
    says "heading unknown")."""
    code, out, err = await run_cli(station, "status", "web-rover")
    assert code == 0, err
    (line,) = [line for line in out.splitlines() if line.startswith("pose")]
    if "heading unknown" in line:
        return None
    found = re.search(r"\s(\d+)°", line)
    assert found, line
    return int(found.group(1))


def battery_reading(text: str | None) -> tuple[float, int]:
    """Volts and percent of the battery readout."""
    found = re.match(r"^(\d+\.\d) V\s+≈(\d+) %", text or "")
    assert found, text
    return float(found.group(1)), int(found.group(2))


async def labels_apart(page: Any) -> list[str]:
    """The map's labels shown, none covering another once the view settles (a zoom animates
    for a quarter second); returns their texts."""
    labels: dict[str, Any] = {}
    await page.evaluate(SETTLED_JS)  # the zoom's animation over, the declutter after it run
    for _ in range(50):
        labels = await page.evaluate(OVERLAP_JS)
        if not labels["overlaps"]:
            return list(labels["shown"])
        await page.wait_for_timeout(100)
    raise AssertionError(f"map labels overlap: {labels}")


async def test_instruments_plots_map_notifications_and_answers(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, browser: Any
) -> None:
    from playwright.async_api import expect

    platform: PlatformDaemon = await rover(
        platform_factory,
        fleet_key,
        station,
        "imu.enabled=true",
        f"sim.heading_deg={HEADING_DEG}",
        # The battery read 5 times a second, not once: each of the 7 steps below waits for
        # the page to show the new voltage.
        "motor.poll_hz=5",
    )
    # A second rover 3 m east of the first, by the demo map's named point "sw": three names
    # that would be written on top of each other.
    await sim_platform(
        platform_factory,
        fleet_key,
        station,
        "web-rover-2",
        23.65303,
        "navcam.enabled=false",
        "audio.enabled=false",
    )
    page = await browser.new_page(viewport={"width": 1366, "height": 768})
    await page.clock.install()  # runs with real time until the test steps it
    await page.goto(f"http://127.0.0.1:{station.api_port}/?platform=web-rover")
    await frames_decoded(page, at_least=5, timeout=30)

    # Heading at rest: neither the localization nor the GPS knows it yet, and the page says
    # so as the CLI does (it used to write the IMU's yaw, counted from power-up, as north).
    heading = page.get_by_label("heading", exact=True)
    await expect(page.get_by_label("attitude")).to_contain_text("roll", timeout=10_000)
    assert await cli_heading(station) is None
    await expect(heading).to_have_text("unknown")

    await expect(page.get_by_label("attitude")).to_have_text(
        re.compile(r"^roll -?\d+\.\d°\s+pitch -?\d+\.\d°$"), timeout=10_000
    )
    await expect(page.get_by_label("ground speed")).to_have_text(re.compile(r"^\d+\.\d km/h$"))
    await expect(page.get_by_label("link quality")).to_have_text(
        re.compile(r"^loss \d+(\.\d+)? %\s+rtt \d+(\.\d+)? ms\s+video \d+\.\d s old$"),
        timeout=15_000,
    )
    cap = page.get_by_label("speed cap", exact=True)
    await expect(cap).to_have_text(re.compile(r"^cap \d+\.\d km/h \(video .*, command .*\)$"))
    reason = page.get_by_label("why this cap")  # in plain sight: text, not a tooltip
    await expect(reason).to_be_visible()
    await expect(reason).to_have_text(re.compile(r"\w{3,}"))
    battery = page.get_by_label("battery", exact=True)
    await expect(battery).to_have_text(re.compile(r"^\d+\.\d V\s+≈\d+ %\s+time left —"))
    volts, percent = battery_reading(await battery.text_content())
    assert abs(percent - (volts / 7 - 3.0) / 1.2 * 100) <= 1, (volts, percent)  # 7 Li-ion cells

    # Not driving: the hint says how, and a drive key says why nothing moves (a sentence on
    # the answer line).
    hint = page.get_by_label("driving hint")
    await expect(hint).to_contain_text("Not driving: engage the override")
    answer = page.locator("#answer")
    await page.locator("body").click(position={"x": 5, "y": 5})
    await page.keyboard.down("KeyW")
    await expect(answer).to_have_text("Nothing moves: engage the override to drive web-rover.")
    assert await page.locator("#stick").get_attribute("data-active") == "false"
    await page.keyboard.up("KeyW")

    # Driving: the hint changes, the stick and the commanded speed follow the key, the
    # ground speed follows the rover.
    override = page.get_by_role("button", name="manual override")
    await override.click()
    await expect(override).to_have_attribute("aria-pressed", "true", timeout=10_000)
    await expect(answer).to_have_text(re.compile(r"^manual override: acknowledged.*\.$"))
    await expect(hint).to_contain_text("Driving: hold W/A/S/D")
    await page.keyboard.down("KeyW")
    try:
        await expect(page.locator("#stick")).to_have_attribute("data-active", "true")
        dot = float(await page.locator("#stick-dot").get_attribute("cy") or "20")
        assert dot < 20, dot  # up: forward
        await expect(page.get_by_label("commanded speed")).to_have_text(
            re.compile(r"^0\.[1-9]\d / -?0\.00$|^1\.00 / -?0\.00$"), timeout=10_000
        )
        await expect(page.get_by_label("ground speed")).not_to_have_text("0.0 km/h", timeout=10_000)
        await expect(heading).to_have_text(re.compile(r"^\d{3}°$"), timeout=15_000)

        def heading_known() -> bool:
            pose = platform.bus.last(topics.POSE)
            return pose is not None and pose.heading_known

        await wait_until(heading_known, timeout=15)  # the localization's, kept once stopped
    finally:
        await page.keyboard.up("KeyW")
    await expect(page.locator("#stick")).to_have_attribute("data-active", "false")
    await expect(page.get_by_label("commanded speed")).to_have_text(
        re.compile(r"^-?0\.00 / -?0\.00$")
    )

    # Heading once known: the CLI's number (clockwise from north: the rover heads 200°, not
    # -110° nor 250°) on the readout and on the needle.
    cli = await cli_heading(station)
    assert cli is not None, cli
    assert abs(cli - HEADING_DEG) <= 20, cli
    near = "|".join(f"{(cli + d) % 360:03d}" for d in (-1, 0, 1))
    await expect(heading).to_have_text(re.compile(rf"^({near})°$"))
    needle = await page.locator("#compass-needle").get_attribute("transform")
    assert needle is not None
    angle = float(re.fullmatch(r"rotate\(([\d.]+) 50 50\)", needle).group(1))  # type: ignore[union-attr]
    assert abs(angle - cli) <= 2, needle

    # Plots: each shown one receives points.
    await expect(page.locator("#plots .uplot")).to_have_count(2, timeout=10_000)
    await page.get_by_role("checkbox", name="speed km/h").check()
    before = await page.evaluate("window.navcam.plotPoints()")
    after = await (
        await page.wait_for_function(
            """(before) => {
              const now = window.navcam.plotPoints();
              return now.speed?.[0] >= 2 && now.volts[0] > before.volts[0] && now.latency[0] > 0 && now;
            }""",
            arg=before,
            timeout=15_000,
        )
    ).json_value()
    assert after["speed"][0] >= 2, after
    await page.get_by_role("checkbox", name="speed km/h").uncheck()  # back to the default two
    await expect(page.locator("#plots .uplot")).to_have_count(2, timeout=5_000)

    # The map: a scale bar; the map takes the main area and gives it back (button and key).
    scale = page.locator("#map .leaflet-control-scale-line")
    await expect(scale).to_have_text(re.compile(r"^\d+ k?m$"))
    swap = page.get_by_role("button", name="swap map and video")
    await swap.click()
    await expect(page.locator("#video-pane > #map")).to_have_count(1)
    await expect(page.locator("#video-box")).to_have_css("position", "fixed")
    await expect(swap).to_have_attribute("aria-pressed", "true")
    await expect(scale).to_be_visible()
    await page.keyboard.press("KeyM")
    await expect(page.locator("#side > #map")).to_have_count(1)
    await expect(page.locator("#video-box")).to_have_css("position", "relative")
    await expect(swap).to_have_attribute("aria-pressed", "false")

    # Map labels: two rovers, the named points and the route's waypoint numbers close
    # together, at every zoom, never
    # written over each other; the shown rover's name always readable.
    await expect(page.locator("#map .platform-icon")).to_have_count(2, timeout=15_000)
    await expect(page.locator("#map .area-point-name")).to_have_count(4, timeout=15_000)
    await expect(page.locator("#map .waypoint-label")).to_have_count(4)  # the demo loop's
    shown = await labels_apart(page)
    assert {"web-rover", "web-rover-2"} <= set(shown), shown
    assert len(shown) >= 7, shown  # of 10
    # Two rovers and the demo field, the heading known: fits both screens (and is
    # docs/console-fleet-*.png).
    await screenshots(page, "console-fleet")
    for width, height in ((1366, 768), (1920, 1080)):  # and no column hides a part below
        await page.set_viewport_size({"width": width, "height": height})
        await page.evaluate(SETTLED_JS)  # the resize handlers and observers have run
        columns = await page.evaluate(
            """["#video-pane", "#middle", "#side"].map((s) => {
              const e = document.querySelector(s); return [s, e.scrollHeight, e.clientHeight];
            })"""
        )
        assert all(scroll <= client + 1 for _, scroll, client in columns), (width, columns)
    await page.set_viewport_size({"width": 1366, "height": 768})
    zoom_out = page.locator("#map .leaflet-control-zoom-out")
    zoom_in = page.locator("#map .leaflet-control-zoom-in")
    for _ in range(4):
        await zoom_in.click()
    shown = await labels_apart(page)
    assert {"web-rover", "web-rover-2"} <= set(shown), shown

    for _ in range(10):
        await zoom_out.click()
        # The declutter runs again as markers move after a zoom: the selected platform's own
        # label must be shown once it has (within 3 s), whatever else gives way.
        for _ in range(30):
            shown = await labels_apart(page)
            if "web-rover" in shown:
                break
            await page.wait_for_timeout(100)
        assert "web-rover" in shown, shown

    # The answer lines speak sentences and expire: the page's clock stepped past their time
    # (from here on the page's clock runs ahead of its video worker's: the checks that need
    # the picture are above).
    await override.click()  # released: the answer is new
    await expect(override).to_have_attribute("aria-pressed", "false", timeout=10_000)
    await expect(answer).to_have_text(re.compile(r"^manual override: acknowledged.*\.$"))
    await page.clock.fast_forward(5_000)
    await expect(answer).not_to_have_text("")
    await page.clock.fast_forward(4_000)
    await expect(answer).to_have_text("", timeout=5_000)
    patrol_answer = page.locator("#patrol-answer")
    await page.get_by_role("button", name="stop patrol").click()
    await expect(patrol_answer).to_have_text("stop patrol: done.", timeout=10_000)
    await page.clock.fast_forward(16_000)
    await expect(patrol_answer).to_have_text("", timeout=5_000)

    # Battery time left: the pack loses 0.2 V a minute (the page's clock stepped a minute
    # between readings): about 11 minutes left at 23.2 V, 2.2 V above empty.
    options = platform.ctx.sim.ax3500.device.options  # type: ignore[union-attr]
    for step in range(1, 8):
        shown = await battery.text_content()
        options.battery_volts = 24.6 - 0.2 * step
        await page.wait_for_function(
            "(shown) => document.querySelector('#battery').textContent.split(' ')[0] !== shown.split(' ')[0]",
            arg=shown,
            timeout=10_000,
        )
        await page.clock.fast_forward(60_000)
    await expect(battery).to_have_text(re.compile(r"≈\d+ min left"), timeout=5_000)
    left = re.search(r"≈(\d+) min left", await battery.text_content() or "")
    assert left, await battery.text_content()
    assert 8 <= int(left.group(1)) <= 14, await battery.text_content()

    # Notifications: a burst is one line counted, a cleared one says so, both kept by the
    # station across a reload, with 24-hour times.
    for _ in range(8):
        station.bus.publish(
            topics.STATION_NOTIFICATIONS,
            StationNotification(
                LINK_LOST, "web-rover", "link_lost", True, "LINK LOST: platform hold", time.time()
            ),
        )
    station.bus.publish(
        topics.STATION_NOTIFICATIONS,
        StationNotification(
            LINK_LOST, "web-rover", "link_lost", False, "LINK LOST: platform hold", time.time()
        ),
    )
    for attempt in ("before", "after reload"):
        burst = page.locator("#notifications li.critical", has_text="LINK LOST: platform hold")
        await expect(burst).to_have_count(1, timeout=10_000)
        await expect(burst).to_contain_text("\u00d78")
        await expect(burst).to_have_text(re.compile(r"^([01]\d|2[0-3]):[0-5]\d:[0-5]\d web-rover"))
        cleared = page.locator("#notifications li.cleared", has_text="LINK LOST: platform hold")
        await expect(cleared).to_have_count(1)
        await expect(cleared).to_contain_text("cleared")
        if attempt == "before":
            await page.reload()
    await page.close()
