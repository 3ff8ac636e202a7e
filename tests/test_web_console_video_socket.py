"""The page's video worker receives the NavCam over a socket of its own, so the frames never
wait for the page's main thread (layout, paint, plots)."""

from __future__ import annotations

from typing import Any

from support.console import Factory, console, frames_decoded, rover

from stationd.daemon import StationDaemon


async def test_the_video_worker_receives_the_navcam_on_its_own_socket(
    station: StationDaemon,
    platform_factory: Factory,
    fleet_key: bytes,
    browser: Any,
) -> None:
    await rover(platform_factory, fleet_key, station)
    page = await console(browser, station, "web-rover")
    decoded = await frames_decoded(page, at_least=10)
    stats = await page.evaluate("window.navcam.stats()")
    assert stats["ownSocket"] > 0, "the frames came through the page's main thread"
    # The switch from the page's socket to the worker's went without a freeze or an error.
    await frames_decoded(page, at_least=decoded + 15)
    stats = await page.evaluate("window.navcam.stats()")
    assert stats["ownSocket"] >= 15
    assert stats["errors"] == 0
