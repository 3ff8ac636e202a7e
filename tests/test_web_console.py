"""The browser console in a real headless Chromium, against a station and a platform on loopback."""

from __future__ import annotations

import shutil
from collections.abc import AsyncIterator, Awaitable, Callable

import pytest
from conftest import free_udp_port, quiet_platform_config, wait_until

from brasidas import topics
from brasidas.config import StationConfig, load_config
from platformd.app import PlatformDaemon
from stationd.daemon import StationDaemon

Factory = Callable[..., Awaitable[PlatformDaemon]]
CHROMIUM = shutil.which("chromium") or "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--no-sandbox",  # tests run as root
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--no-first-run",
    "--disable-sync",
]


@pytest.fixture
async def station(fleet_key: bytes) -> AsyncIterator[StationDaemon]:
    config = load_config(
        StationConfig,
        None,
        [
            "station.api_port=0",
            f"discovery.port={free_udp_port()}",
            "discovery.bind_host=127.0.0.1",
        ],
    )
    daemon = StationDaemon(config, fleet_key)
    await daemon.start()
    yield daemon
    await daemon.stop()


async def test_console_lists_connects_and_takes_the_override(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes
) -> None:
    from playwright.async_api import async_playwright, expect

    config = quiet_platform_config(
        "platform.id=web-rover",
        "beacon.enabled=true",
        f"beacon.port={station.config.discovery.port}",
        'beacon.destinations=["127.0.0.1"]',
        "beacon.listen=false",  # unicast: the station alone must hold the port
        "beacon.max_interval=1.0",
        "sim.enabled=true",  # a simulated GPS receiver behind the real reader
        "gps.enabled=true",
    )
    platform = await platform_factory(config, fleet_key)
    async with async_playwright() as playwright:
        browser = await playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = await browser.new_page()
            errors: list[str] = []
            page.on("pageerror", lambda error: errors.append(str(error)))
            await page.goto(f"http://127.0.0.1:{station.api_port}/")
            row = page.locator('#platforms tr[data-platform="web-rover"]')
            await expect(row).to_contain_text("web-rover", timeout=10_000)
            await row.locator("button.connect").click()
            override = page.get_by_role("button", name="manual override")
            await expect(override).to_have_text("override: autonomous", timeout=10_000)
            await expect(override).to_have_attribute("aria-pressed", "false")
            await override.click()
            await expect(override).to_have_text("override: ENGAGED", timeout=10_000)
            await expect(override).to_have_attribute("aria-pressed", "true")
            await wait_until(lambda: platform.bus.last(topics.OVERRIDE_STATE).engaged)
            await expect(page.locator("#answer")).to_contain_text("acknowledged")
            await expect(page.locator("#driving")).to_have_text("this console is driving web-rover")
            # Telemetry reaches the page: the computer section, and the simulated GPS fix.
            telemetry = page.locator("dl#status")
            await expect(telemetry).to_contain_text("free", timeout=10_000)
            await expect(telemetry).to_contain_text("sats  hdop", timeout=10_000)
            await expect(telemetry).to_contain_text("37.94", timeout=10_000)
            await override.click()
            await wait_until(lambda: not platform.bus.last(topics.OVERRIDE_STATE).engaged)
            await expect(page.locator("#driving")).to_have_text("not driving")
            assert errors == []
        finally:
            await browser.close()
