"""The console's video overlay shows the feed's bitrate and its repair counters (issue 28)."""

from __future__ import annotations

import re
from typing import Any

from support.console import FRAMES_COUNTED, Factory, console, frames_decoded, rover

from stationd.daemon import StationDaemon


async def test_the_overlay_shows_the_bitrate_and_repairs(
    station: StationDaemon,
    platform_factory: Factory,
    fleet_key: bytes,
    browser: Any,
) -> None:
    from playwright.async_api import expect

    await rover(platform_factory, fleet_key, station, FRAMES_COUNTED)
    page = await console(browser, station, "web-rover")
    await frames_decoded(page, at_least=10)
    link = page.get_by_label("video link")
    await expect(link).to_have_text(
        re.compile(r"^[1-9]\d* kbit/s · \d+ repaired · \d+ lost$"), timeout=10_000
    )
