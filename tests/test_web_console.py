"""The browser console in a real headless Chromium, against a station and a platform on loopback."""

from __future__ import annotations

import re
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

import pytest_asyncio
from conftest import free_tcp_port, quiet_platform_config, running_station, wait_until

from brasidas import topics
from brasidas.codecs.telemetry_schema import schema_document
from platformd.app import PlatformDaemon
from stationd.daemon import StationDaemon

Factory = Callable[..., Awaitable[PlatformDaemon]]
MISSING_CHIP = "/dev/gpiochip-brasidas-console-missing"
# Wraps every telemetry report's snapshot (answered or pushed) in proxies that record each field the page reads
# ("gps.sats"), so the test can check the names against the schema the station serves.
RECORD_READS = """
window.__telemetryReads = new Set();
const record = (value, path, depth) => {
  if (value === null || typeof value !== "object" || Array.isArray(value) || depth > 3) return value;
  return new Proxy(value, {
    get(target, key, receiver) {
      const item = Reflect.get(target, key, receiver);
      if (typeof key !== "string") return item;
      const name = path ? `${path}.${key}` : key;
      window.__telemetryReads.add(name);
      return record(item, name, depth + 1);
    },
  });
};
const parse = JSON.parse;
JSON.parse = function (text, reviver) {
  const value = parse.call(this, text, reviver);
  for (const report of [value?.result, value?.params]) {
    if (report && typeof report === "object" && "snapshot" in report) {
      report.snapshot = record(report.snapshot, "", 0);
    }
  }
  return value;
};
"""


@pytest_asyncio.fixture(loop_scope="session")  # its one test is a browser test
async def station(fleet_key: bytes) -> AsyncIterator[StationDaemon]:
    async with running_station(fleet_key) as daemon:
        yield daemon


async def test_console_lists_connects_and_takes_the_override(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, browser: Any
) -> None:
    from playwright.async_api import expect

    config = quiet_platform_config(
        "platform.id=web-rover",
        "beacon.enabled=true",
        f"beacon.port={station.config.discovery.port}",
        'beacon.destinations=["127.0.0.1"]',
        "beacon.listen=false",  # unicast: the station alone must hold the port
        "beacon.max_interval=1.0",
        "sim.enabled=true",  # a simulated GPS receiver behind the real reader
        "gps.enabled=true",
        "motor.enabled=true",
        f"motor.positional_lights_output=gpio:{MISSING_CHIP}:17",  # libgpiod's own refusal
        'payload.enabled=["turret"]',  # its simulated microcontroller on a pty
        "payload_camera.enabled=true",  # the turret's sight; offline, never started here
        f"payload_camera.url=rtsp://127.0.0.1:{free_tcp_port()}/thermal",
    )
    platform = await platform_factory(config, fleet_key)
    page = await browser.new_page()
    await page.add_init_script(RECORD_READS)
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
    # A light whose GPIO chip does not exist says it cannot be switched, and why.
    lights_error = page.get_by_role("status", name="lights error")
    await expect(lights_error).to_have_text(
        "lights cannot be switched: positional: cannot request GPIO line "
        f"{MISSING_CHIP}:17: no such GPIO chip (No such file or directory)",
        timeout=10_000,
    )
    await expect(page.locator("#lights-pos")).to_have_attribute("data-error", "true")
    await expect(page.locator("#lights-main")).to_have_attribute("data-error", "")
    # The turret: where it points and its sight's stream state; then its microcontroller
    # is unplugged: LINE DOWN and the platform's reason.
    turret = page.get_by_label("turret", exact=True)
    await expect(turret).to_contain_text("trigger safe", timeout=10_000)
    await expect(turret).to_contain_text("sight payload_camera idle")
    assert platform.ctx.sim.turret is not None
    platform.ctx.sim.turret.close()
    await expect(turret).to_have_attribute("data-line", "down", timeout=10_000)
    await expect(turret).to_contain_text(
        re.compile(r"turret:  LINE DOWN: (\S+: serial line closed|cannot open \S+)")
    )
    await expect(turret).to_contain_text("sight payload_camera idle")
    await expect(turret).not_to_contain_text("trigger")
    await override.click()
    await wait_until(lambda: not platform.bus.last(topics.OVERRIDE_STATE).engaged)
    await expect(page.locator("#driving")).to_have_text("not driving")
    # The receiver falls silent: the last fix stays on screen, marked stale with its age.
    assert platform.ctx.sim.gps is not None
    platform.ctx.sim.gps.close()
    gps_row = page.locator("dl#status dt:text-is('gps') + dd")
    await expect(gps_row).to_contain_text("STALE (", timeout=15_000)
    await expect(gps_row).to_contain_text("s old)")
    assert errors == []

    # Every telemetry field the page read is one the schema has (a renamed field fails
    # here, not as a "?" on the operator's screen).
    base = f"http://127.0.0.1:{station.api_port}"
    answer = await page.request.get(f"{base}/api/telemetry-schema.json")
    document = await answer.json()
    assert document == schema_document()
    reads = set(await page.evaluate("[...window.__telemetryReads]"))
    unknown = sorted(name for name in reads if not known(document, name))
    assert unknown == [], f"console.js reads fields the schema does not have: {unknown}"
    assert {"gps.sats", "gps.lat", "battery", "computer.mem_free_mb"} <= reads
    assert {"lights.errors", "turret.streams", "turret.error"} <= reads


def known(document: dict[str, Any], path: str) -> bool:
    """``path`` (section.field.nested...) names a field of the schema, or an entry of a map.

    ``error`` is every section's error (``{"error": why}``, see telemetry_schema)."""
    section, *names = path.split(".")
    entry = document["sections"].get(section)
    if entry is None:
        return False
    fields = entry["fields"]
    for index, name in enumerate(names):
        if index == 0 and name == "error":
            return True
        field = fields.get(name)
        if field is None:
            return False
        if field["type"].startswith("map["):
            return True  # any key of a map (stream names)
        fields = field.get("fields", {})
    return True


def test_the_field_check_catches_a_renamed_field() -> None:
    document = schema_document()
    assert known(document, "gps.sats")
    assert known(document, "streams.states.navcam")
    assert known(document, "attitude.imu.temp_c")
    assert known(document, "computer.error")
    assert not known(document, "gps.satellites")
    assert not known(document, "gps.stats.port")
    assert known(document, "autonomy.reason")
    assert not known(document, "autonomy.target")
