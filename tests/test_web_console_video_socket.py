"""The page's video worker receives the NavCam over a socket of its own, so the frames never
wait for the page's main thread (layout, paint, plots)."""

from __future__ import annotations

from typing import Any

from support.console import FRAMES_COUNTED, Factory, console, frames_decoded, rover
from support.png import png_pixels

from stationd.daemon import StationDaemon


async def test_the_video_worker_receives_the_navcam_on_its_own_socket(
    station: StationDaemon,
    platform_factory: Factory,
    fleet_key: bytes,
    browser: Any,
) -> None:
    # 25 frames counted: at 15 fps, not the idle 5, they take under 2 s instead of 5.
    await rover(platform_factory, fleet_key, station, FRAMES_COUNTED)
    page = await console(browser, station, "web-rover")
    decoded = await frames_decoded(page, at_least=10)
    stats = await page.evaluate("window.navcam.stats()")
    assert stats["ownSocket"] > 0, "the frames came through the page's main thread"
    # The switch from the page's socket to the worker's went without a freeze or an error.
    await frames_decoded(page, at_least=decoded + 15)
    stats = await page.evaluate("window.navcam.stats()")
    assert stats["ownSocket"] >= 15
    assert stats["errors"] == 0


BARS = ((1, 1, 1), (1, 1, 0), (0, 1, 1), (0, 1, 0), (1, 0, 1), (1, 0, 0), (0, 0, 1))
"""videotestsrc's SMPTE bars, left to right: which of red, green, blue are lit (white, yellow,
cyan, green, magenta, red, blue)."""


async def test_the_worker_draws_the_frames_pixels_converted_once(
    station: StationDaemon,
    platform_factory: Factory,
    fleet_key: bytes,
    browser: Any,
) -> None:
    """Each frame's pixels are converted to RGBA by the browser (VideoFrame.copyTo, one pass)
    and put on the canvas, not drawn as an image (a second conversion, twice the time): in the
    right colours, red and blue where they belong."""
    await rover(platform_factory, fleet_key, station, "navcam.sim_motion=0", FRAMES_COUNTED)
    page = await console(browser, station, "web-rover")
    decoded = await frames_decoded(page, at_least=10)
    stats = await page.evaluate("window.navcam.stats()")
    assert stats["copied"] >= decoded - 5, stats  # the first few may be drawn before the stats
    assert stats["errors"] == 0
    # One strip across the bars' upper part (below the sim's clock), as the screen shows it.
    box = await page.locator("#video").bounding_box()
    assert box is not None
    strip = {"x": box["x"], "y": box["y"] + box["height"] * 0.4, "width": box["width"], "height": 2}
    row = png_pixels(await page.screenshot(clip=strip))[0]
    for index, expected in enumerate(BARS):
        seen = row[int(len(row) * (index + 0.5) / len(BARS))]
        lit = tuple(int(level > 128) for level in seen)
        assert lit == expected, f"bar {index}: {seen}"
