"""Smaller console items of issue 31 (second wave) in headless Chromium: a video pause raises
an information note (it raised none), and its resumption another."""

from __future__ import annotations

from typing import Any

from support.console import Factory, console, frames_decoded, rover

from stationd.daemon import StationDaemon


async def test_a_video_pause_and_its_resumption_are_noted(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, browser: Any
) -> None:
    from playwright.async_api import expect

    await rover(platform_factory, fleet_key, station)
    page = await console(browser, station, "web-rover")
    await frames_decoded(page, at_least=3)
    notes = page.locator("#notifications li")
    await station.ctx.api.call_local("stream_pause", platform_id="web-rover", stream="navcam")
    paused = notes.filter(has_text="navcam paused: the picture is held")
    await expect(paused).to_have_count(1, timeout=10_000)
    await expect(paused).to_have_class("note info")  # routine: not a warning, not flashed
    await expect(page.locator("#annunciator button")).to_have_count(0)
    await station.ctx.api.call_local("stream_start", platform_id="web-rover", stream="navcam")
    await expect(notes.filter(has_text="navcam playing again")).to_have_count(1, timeout=10_000)
