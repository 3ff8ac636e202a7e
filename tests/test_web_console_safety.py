"""The console's safety parts (issue 27) in headless Chromium against a --sim platform: the
STOP every operator has (this station does not hold control), and a platform gone silent
greyed out with its age and said in a notification within 3 s, unmarked when it is back."""

from __future__ import annotations

import re
from typing import Any

from conftest import wait_until
from support.console import FRAMES_COUNTED, Factory, console, frames_decoded, rover

from stationd.daemon import StationDaemon


async def test_stop_for_an_observer_and_a_silent_platform_greyed_with_its_age(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, browser: Any
) -> None:
    from playwright.async_api import expect

    platform = await rover(platform_factory, fleet_key, station, FRAMES_COUNTED)
    page = await console(browser, station, "web-rover")
    panel = page.locator("#instruments")
    await expect(page.get_by_label("heading")).not_to_have_text("—", timeout=15_000)
    await expect(panel).not_to_have_class(re.compile("silent"))
    await frames_decoded(page, at_least=5)
    stale = page.get_by_role("alert", name="video stale")

    # Telemetry stops (its datagrams dropped at the station, as when the platform is killed).
    (receiver,) = [a for a in station.supervisor.actors if a.name == "telemetry"]
    link = receiver.links["web-rover"]
    link.datagram_received = lambda data, addr: None  # on the instance only
    try:
        await expect(panel).to_have_class(re.compile("silent"), timeout=3_500)
        await expect(page.locator("#instruments-age")).to_have_text(
            re.compile(r"platform silent \d+\.\d s: the last values shown")
        )
        note = page.locator("#notifications li", has_text="platform silent: no telemetry")
        await expect(note.first).to_be_visible(timeout=2_000)
        # The picture stops too (a restarted platform has lost the stream).
        await station.ctx.api.call_local("stream_pause", platform_id="web-rover", stream="navcam")
        await expect(stale).to_be_visible(timeout=5_000)
    finally:
        del link.datagram_received
    await expect(panel).not_to_have_class(re.compile("silent"), timeout=10_000)
    # Back: the page asks for the picture again by itself (it stayed "NO VIDEO" until a click).
    decoded = await frames_decoded(page, at_least=1)
    await frames_decoded(page, at_least=decoded + 10)
    await expect(stale).to_be_hidden(timeout=5_000)
    cleared = page.locator("#notifications li.cleared", has_text="platform silent")
    await expect(cleared.first).to_be_visible(timeout=5_000)

    # STOP: this station holds no control; the platform stops and says who.
    arming = platform.ctx.arming
    assert arming is not None
    await page.get_by_role("button", name="emergency stop").click()
    await wait_until(lambda: arming.last_word is not None and arming.last_word.word == "stop")
    assert arming.last_word is not None
    assert arming.last_word.by == station.ctx.config.station.id
    await expect(page.locator("#answer")).to_contain_text("STOP: web-rover stopped")


async def test_a_closed_driving_page_releases_its_override_after_the_deadman(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, browser: Any
) -> None:
    """Before: the override stayed engaged (the station's heartbeats kept it) and the patrol
    suspended for as long as the station ran."""
    from playwright.async_api import expect

    from brasidas import topics

    platform = await rover(platform_factory, fleet_key, station)
    page = await console(browser, station, "web-rover")
    override = page.get_by_role("button", name="manual override")
    await expect(override).to_be_enabled(timeout=15_000)
    await override.click()

    def engaged() -> bool:
        state = platform.bus.last(topics.OVERRIDE_STATE)
        return state is not None and state.engaged

    await wait_until(engaged, 10)
    await page.close()
    await wait_until(lambda: not engaged(), 5)


async def test_releasing_the_override_over_a_waiting_patrol_asks_first(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, browser: Any
) -> None:
    """Before: releasing the override with a patrol suspended drove off at once, unsaid."""
    from playwright.async_api import expect

    from brasidas import topics

    platform = await rover(platform_factory, fleet_key, station)
    arming = platform.ctx.arming
    assert arming is not None
    page = await console(browser, station, "web-rover")
    await expect(page.get_by_role("button", name="start patrol")).to_be_enabled(timeout=15_000)
    await wait_until(lambda: not arming.reasons(), 20)  # a start arms through the checks
    await page.get_by_role("button", name="start patrol").click()
    await page.get_by_label("slide to confirm start patrol").fill("100")  # issue 31's slide
    await wait_until(lambda: arming.armed, 10)

    def engaged() -> bool:
        state = platform.bus.last(topics.OVERRIDE_STATE)
        return state is not None and state.engaged

    override = page.get_by_role("button", name="manual override")
    await override.click()
    await wait_until(engaged, 10)
    await expect(page.locator("#patrol-state")).to_contain_text("suspended", timeout=10_000)
    confirm = page.get_by_role("group", name="confirm release")
    await override.click()
    await expect(confirm).to_be_visible()
    await expect(confirm).to_contain_text("The patrol resumes toward waypoint")
    await expect(confirm).to_contain_text(re.compile(r"at once, at \d+(\.\d)? km/h"))
    assert engaged()  # nothing released yet
    await page.get_by_role("button", name="keep the override").click()
    await expect(confirm).to_be_hidden()
    assert engaged()
    await override.click()
    await page.get_by_role("button", name="confirm release").click()
    await wait_until(lambda: not engaged(), 10)
