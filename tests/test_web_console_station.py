"""The operator's whole station in a real headless Chromium, end to end against two --sim
platforms on loopback: map and list, NavCam decoded in the page's Worker, override, driving
with the keyboard, stopping on release and on blur, switching platforms, disconnecting.

One browser and one page for the whole scenario (each launch costs seconds here)."""

from __future__ import annotations

import asyncio
import json
import os
import re
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from conftest import (
    running_station,
    velocities_accepted,
    velocities_dropped,
    wait_until,
)
from support.console import (
    FRAMES_COUNTED,
    Factory,
    frames_decoded,
    platforms_in_view,
    sim_platform,
)

from brasidas import topics
from brasidas.autonomy.geo import LocalFrame
from brasidas.messages import FailsafeStep
from stationd.client import PlatformConnection
from stationd.daemon import StationDaemon

FAKE_GAMEPAD = """
(() => {
  // A standard-mapping game controller the test moves: window.__pad.
  const pad = { connected: false, axes: [0, 0, 0, 0], pressed: new Array(17).fill(false) };
  window.__pad = pad;
  pad.polls = 0; // how often the page has read it
  navigator.getGamepads = () => (pad.polls++, pad.connected) ? [{
    id: "fake F310", index: 0, mapping: "standard", connected: true, timestamp: performance.now(),
    axes: pad.axes.slice(), buttons: pad.pressed.map((p) => ({ pressed: p, touched: p, value: p ? 1 : 0 })),
  }] : [];
})();
"""
SCREENSHOT = Path(__file__).resolve().parent.parent / "docs" / "console.png"
"""The docs' screenshots (docs/operator-guide.md): written when BRASIDAS_SCREENSHOT=1."""


@pytest.fixture
def station_settings() -> tuple[str, ...]:
    # The CLI's drive timeout far away: only the console's own stops can stop the robot in time.
    return ("teleop.drive_timeout=30",)


class LinkCut:
    """The station's link to one platform goes silent both ways, as a radio out of range would
    (loopback has no cable to pull): its signaling calls, heartbeats included, wait for the link
    to come back (a stalled connection); its velocity sender sends nothing; the platform's
    telemetry datagrams are dropped at the station's socket."""

    def __init__(self, station: StationDaemon, platform_id: str) -> None:
        self.station = station
        self.platform_id = platform_id
        self.up = asyncio.Event()
        self.up.set()
        self.patched: list[tuple[object, str]] = []

    def _actor(self, name: str) -> Any:
        (actor,) = [a for a in self.station.supervisor.actors if a.name == name]
        return actor

    def cut(self) -> None:
        connection = self.station.ctx.connections[self.platform_id]
        call = connection.call

        async def stalled(method: str, **params: Any) -> Any:
            await self.up.wait()
            return await call(method, **params)

        self.up.clear()
        self._patch(connection, "call", stalled)
        self._patch(self._actor("teleop").senders[self.platform_id], "tick", lambda: None)
        self._patch(
            self._actor("telemetry").links[self.platform_id],
            "datagram_received",
            lambda data, addr: None,
        )

    def _patch(self, target: object, name: str, replacement: object) -> None:
        setattr(target, name, replacement)  # on the instance: the class's method is untouched
        self.patched.append((target, name))

    def restore(self) -> None:
        for target, name in self.patched:
            delattr(target, name)
        self.patched.clear()
        self.up.set()


async def telemetry_position(station: StationDaemon, platform_id: str) -> tuple[float, float]:
    """The platform's position in its telemetry (the report the page is pushed)."""
    report = await station.ctx.api.call_local("get_telemetry", platform_id=platform_id)
    gps = report["snapshot"]["gps"]
    return (gps["lat"], gps["lon"])


async def wait_moved(station: StationDaemon, platform_id: str, start: tuple[float, float]) -> None:
    """Wait until the platform's telemetry position differs from ``start``."""
    for _ in range(100):
        if await telemetry_position(station, platform_id) != start:
            return
        await asyncio.sleep(0.1)
    raise AssertionError(f"{platform_id}'s telemetry position did not change in 10 s")


async def planned_path(station: StationDaemon, platform_id: str) -> list[tuple[float, float]]:
    report = await station.ctx.api.call_local("get_telemetry", platform_id=platform_id)
    return [(lat, lon) for lat, lon in report["snapshot"]["autonomy"]["path"]]


def local_path(frame: LocalFrame, path: list[tuple[float, float]]) -> list[tuple[float, float]]:
    return [frame.to_local(lat, lon) for lat, lon in path]


async def draw_polygon(page: Any, corners: list[tuple[float, float]]) -> None:
    """Click each [lat, lon] corner on the map, as the operator draws a keep-out."""
    box = await page.locator("#map").bounding_box()
    assert box is not None
    for index, (lat, lon) in enumerate(corners, start=1):
        at = await page.evaluate(f"window.navcam.mapPixel({lat}, {lon})")
        await page.mouse.click(box["x"] + at["x"], box["y"] + at["y"])
        await expect_count(page.locator(f'#map [title="corner {index}"]'), 1)


async def expect_count(locator: Any, count: int, timeout: float = 10_000) -> None:
    from playwright.async_api import expect

    await expect(locator).to_have_count(count, timeout=timeout)


async def keep_out_zones_drawn_and_removed(
    page: Any, station: StationDaemon, platform_id: str
) -> None:
    """The operator draws a keep-out on the patrol's planned path and sends it: the platform's
    map has it and the path goes around it; it is removed again; a self-intersecting one is
    refused with the platform's reason and the map stays as it was."""
    from playwright.async_api import expect
    from shapely.geometry import LineString, Polygon, box

    patrol_answer = page.locator("#patrol-answer")
    keepouts = page.get_by_role("list", name="keep-out zones of the platform")
    await expect(keepouts.locator("li")).to_have_count(1)  # the demo field's shed
    await expect(keepouts).to_contain_text("keep-out shed")
    # A 4 m square on the planned path 6 m before its end (the target waypoint), once the
    # path is 20 m long or more: well ahead of the robot, which keeps patrolling meanwhile.
    frame = LocalFrame(*(await planned_path(station, platform_id))[0])
    loop = asyncio.get_running_loop()
    deadline = loop.time() + 30
    while (
        path := LineString(local_path(frame, await planned_path(station, platform_id)))
    ).length < 20:
        assert loop.time() < deadline, f"no planned path of 20 m in 30 s: {path}"
        await asyncio.sleep(0.2)
    centre = path.interpolate(path.length - 6)
    zone = box(centre.x - 2, centre.y - 2, centre.x + 2, centre.y + 2)
    square = [frame.to_geo(x, y) for x, y in list(zone.exterior.coords)[:4]]
    draw = page.get_by_role("button", name="draw keep-out")
    await draw.click()
    await expect(draw).to_have_attribute("aria-pressed", "true")
    await page.get_by_label("name", exact=True).fill("crater")
    send = page.get_by_role("button", name="send keep-out")
    await expect(send).to_be_disabled()  # no polygon yet
    await draw_polygon(page, square)
    await expect(page.locator("#map path.keepout-draft")).to_have_count(1)
    await expect(page.locator("#map path.area-keepout")).to_have_count(1)  # a draft, not sent
    await send.click()
    await expect(patrol_answer).to_contain_text("keep-out sent", timeout=10_000)
    await expect(send).to_be_hidden()
    area = await station.ctx.api.call_local("map_get", platform_id=platform_id)
    assert {f.get("id") for f in area["map"]["features"]} >= {"shed", "crater"}
    await expect(page.locator("#map path.area-keepout")).to_have_count(2, timeout=10_000)
    await expect(page.locator("#map path.keepout-draft")).to_have_count(0)
    await expect(keepouts.locator('li[data-keepout="crater"]')).to_have_count(1)
    # The platform replans around it (its planned path in telemetry, not the page's guess).
    deadline = loop.time() + 10
    while (
        path := LineString(local_path(frame, await planned_path(station, platform_id)))
    ).intersects(zone):
        assert loop.time() < deadline, f"the planned path still crosses the keep-out: {path}"
        await asyncio.sleep(0.1)

    # Removed from the list: the platform's map no longer has it.
    await page.get_by_role("button", name="remove keep-out crater").click()
    await expect(patrol_answer).to_contain_text("keep-out crater removed", timeout=10_000)
    await expect(keepouts.locator('li[data-keepout="crater"]')).to_have_count(0, timeout=10_000)
    await expect(page.locator("#map path.area-keepout")).to_have_count(1)
    area = await station.ctx.api.call_local("map_get", platform_id=platform_id)
    assert "crater" not in {f.get("id") for f in area["map"]["features"]}
    # Changed elsewhere (as the CLI does, through the station's API): the page redraws when
    # telemetry's map revision moves.
    rock = {
        "type": "Feature",
        "id": "rock",
        "properties": {"role": "keepout"},
        "geometry": {"type": "Polygon", "coordinates": [[[lon, lat] for lat, lon in square]]},
    }
    rock["geometry"]["coordinates"][0].append(rock["geometry"]["coordinates"][0][0])
    await station.ctx.api.call_local("map_update", platform_id=platform_id, add=[rock])
    await expect(keepouts.locator('li[data-keepout="rock"]')).to_have_count(1, timeout=10_000)
    await expect(page.locator("#map path.area-keepout")).to_have_count(2)
    await station.ctx.api.call_local("map_update", platform_id=platform_id, remove=["rock"])
    await expect(keepouts.locator('li[data-keepout="rock"]')).to_have_count(0, timeout=10_000)
    await expect(page.locator("#map path.area-keepout")).to_have_count(1)

    # A bow tie (its edges cross), drawn over the shed (where the robot never is): refused
    # with the platform's reason; the map is unchanged and the draft stays open to correct,
    # until cancelled.
    (shed,) = [f for f in area["map"]["features"] if f.get("id") == "shed"]
    x, y = Polygon(
        [frame.to_local(lat, lon) for lon, lat in shed["geometry"]["coordinates"][0]]
    ).centroid.coords[0]
    tie = [frame.to_geo(x + dx, y + dy) for dx, dy in ((-2, -2), (2, 2), (2, -2), (-2, 2))]
    await draw.click()
    await draw_polygon(page, tie)
    await send.click()
    await expect(patrol_answer).to_contain_text("send keep-out: update refused:", timeout=10_000)
    await expect(patrol_answer).to_contain_text("self-intersection")
    await expect(page.locator("#map path.keepout-draft")).to_have_count(1)
    await expect(page.locator("#map path.area-keepout")).to_have_count(1)
    area = await station.ctx.api.call_local("map_get", platform_id=platform_id)
    assert [f.get("id") for f in area["map"]["features"] if "id" in f] == ["shed"]
    await page.get_by_role("button", name="cancel keep-out").click()
    await expect(page.locator("#map path.keepout-draft")).to_have_count(0)


async def test_operator_station_in_the_browser(
    station: StationDaemon,
    platform_factory: Factory,
    fleet_key: bytes,
    tmp_path: Path,
    browser: Any,
) -> None:
    from playwright.async_api import expect

    rover = await sim_platform(
        platform_factory, fleet_key, station, "web-rover", 23.6530, FRAMES_COUNTED
    )
    other = await sim_platform(
        platform_factory,
        fleet_key,
        station,
        "rover-2",
        23.6545,
        FRAMES_COUNTED,
        'payload.enabled=["turret"]',
        # The silent intruder below holds control (the failsafe's hold) until this console
        # takes it: its session must not end first (after the default 5 s, which is only 3.5 s
        # past the hold: too short a window for the page's steps on a loaded machine).
        "signaling.session_timeout=60",
        "failsafe.release_after=60",
    )
    base = f"http://127.0.0.1:{station.api_port}"
    async with aiohttp.ClientSession() as http, http.get(base + "/") as response:
        policy = response.headers["Content-Security-Policy"]
        assert "script-src 'self'" in policy
        assert "unsafe-inline" not in policy
        assert "<script>" not in await response.text()  # no inline script

    page = await browser.new_page(viewport={"width": 1280, "height": 860})
    await page.add_init_script(FAKE_GAMEPAD)
    errors: list[str] = []
    page.on("pageerror", lambda error: errors.append(str(error)))
    page.on(
        "console",
        lambda m: errors.append(m.text) if "Content Security Policy" in m.text else None,
    )
    await page.goto(base + "/")

    # Both platforms in the list and on the map (Leaflet from Debian's package).
    for name in ("web-rover", "rover-2"):
        await expect(page.locator(f'#platforms tr[data-platform="{name}"]')).to_be_visible(
            timeout=10_000
        )
    await expect(page.locator("#map .platform-icon")).to_have_count(2, timeout=10_000)
    # Both in sight: the view follows the platforms until the operator takes it (the
    # first alone used to be centred, leaving rover-2's neighbour 130 m away off the map).
    await platforms_in_view(page)
    # Offline backgrounds the operator loads: a GeoJSON area, an image with its corners.
    area = tmp_path / "area.geojson"
    area.write_text(
        json.dumps(
            {
                "type": "Feature",
                "properties": {"role": "boundary"},
                "geometry": {
                    "type": "Polygon",
                    "coordinates": [
                        [
                            [23.652, 37.941],
                            [23.655, 37.941],
                            [23.655, 37.943],
                            [23.652, 37.941],
                        ]
                    ],
                },
            }
        )
    )
    files = page.get_by_text("map files and background")
    await files.click()  # folded at first
    await page.locator("#map-geojson").set_input_files(str(area))
    await expect(page.locator("#map path.area-background")).to_have_count(1)
    await page.locator("#map-bounds").fill("37.940,23.651,37.943,23.656")
    await page.locator("#map-image").set_input_files(str(SCREENSHOT))
    await expect(page.locator("#map img.area-image")).to_have_count(1)
    await expect(page.locator("#map path.area-background")).to_have_count(0)  # replaced
    await page.locator("#map-clear").click()
    await files.click()  # folded again
    await expect(page.locator("#map img.area-image")).to_have_count(0)

    # Click the platform on the map: connected, and its NavCam decoded in the Worker.
    await platforms_in_view(page)
    await page.locator("#map .platform-icon", has_text="web-rover").click()
    video = page.get_by_label("NavCam web-rover")
    await expect(video).to_be_visible(timeout=10_000)
    await frames_decoded(page, at_least=15)
    latency = page.get_by_label("glass-to-glass latency")
    await expect(latency).to_have_text(re.compile(r"^\d+\.\d ms$"), timeout=5_000)
    assert float(await latency.get_attribute("data-ms") or "nan") > 0
    assert "web-rover" in station.ctx.connections

    # Take the override: this console drives.
    override = page.get_by_role("button", name="manual override")
    await override.click()
    await expect(override).to_have_attribute("aria-pressed", "true", timeout=10_000)
    await expect(page.locator("#driving")).to_have_text("this console is driving web-rover")
    await wait_until(lambda: rover.bus.last(topics.OVERRIDE_STATE).engaged)
    vehicle = rover.ctx.sim.vehicle
    assert vehicle is not None

    # Hold W: the robot moves (its position in telemetry changes); release: it stops.
    start = await telemetry_position(station, "web-rover")
    await page.keyboard.down("KeyW")
    await wait_until(lambda: vehicle.command[0] > 0.3, timeout=15)
    await wait_moved(station, "web-rover", start)
    await page.keyboard.up("KeyW")
    await wait_until(lambda: vehicle.command == (0.0, 0.0), timeout=2)

    # Drive again, then the page loses focus: it stops without a key release.
    await page.keyboard.down("KeyW")
    await wait_until(lambda: vehicle.command[0] > 0.3, timeout=15)
    await page.evaluate("window.dispatchEvent(new Event('blur'))")
    await wait_until(lambda: vehicle.command == (0.0, 0.0), timeout=2)
    await page.keyboard.up("KeyW")

    # The game controller: the stick moves the robot only while LB (enable) is held.
    polls = await page.evaluate(
        "window.__pad.connected = true; window.__pad.axes[1] = -1; window.__pad.polls"
    )
    # A move would show by now: the page has read the stick (LB up) three times, and
    # three velocity packets have reached the platform since.
    async with asyncio.timeout(10):  # polled from here: the CSP forbids wait_for_function
        while await page.evaluate("window.__pad.polls") < polls + 3:
            await asyncio.sleep(0.02)
    accepted = velocities_accepted(rover)
    await wait_until(lambda: velocities_accepted(rover) >= accepted + 3, timeout=10)
    assert vehicle.command == (0.0, 0.0), "moved without the enable button"
    await page.evaluate("window.__pad.pressed[4] = true")
    await wait_until(lambda: vehicle.command[0] > 0.9, timeout=15)
    await page.evaluate("window.__pad.pressed[4] = false")
    await wait_until(lambda: vehicle.command == (0.0, 0.0), timeout=2)
    await page.evaluate("window.__pad.pressed[4] = true")
    await wait_until(lambda: vehicle.command[0] > 0.9, timeout=15)
    await page.evaluate(  # unplugged while driving
        "window.__pad.connected = false;window.dispatchEvent(new Event('gamepaddisconnected'))"
    )
    await wait_until(lambda: vehicle.command == (0.0, 0.0), timeout=2)
    # A toggles the override: released, then engaged again.
    await page.evaluate("Object.assign(window.__pad, {connected: true, axes: [0, 0, 0, 0]})")
    await page.evaluate("window.__pad.pressed.fill(false); window.__pad.pressed[0] = true")
    await wait_until(lambda: not rover.bus.last(topics.OVERRIDE_STATE).engaged)
    await page.evaluate("window.__pad.pressed[0] = false")
    await expect(override).to_have_attribute("aria-pressed", "false", timeout=10_000)
    # Answered (no longer pending: a press meanwhile would be ignored), then engage.
    await expect(override).to_have_text("override: autonomous", timeout=10_000)
    await page.evaluate("window.__pad.pressed[0] = true")
    await expect(override).to_have_attribute("aria-pressed", "true", timeout=10_000)
    await page.evaluate("window.__pad.pressed[0] = false")

    # Each stream's controls: pause the NavCam, start it again into the page.
    navcam = page.locator('#streams tr[data-stream="navcam"]')
    await navcam.get_by_role("button", name="pause navcam").click()
    await expect(navcam).to_contain_text("navcam: paused", timeout=10_000)
    decoded = await frames_decoded(page, at_least=1)
    await navcam.get_by_role("button", name="start navcam").click()
    await expect(navcam).to_contain_text("navcam: playing", timeout=10_000)
    await frames_decoded(page, at_least=decoded + 10)
    # Framerate (10.5), diagnostics (20.0), battery monitor (20.4): acknowledged.
    answer = page.locator("#answer")
    await page.locator("#framerate").fill("10")
    await page.get_by_role("button", name="set").click()
    await expect(answer).to_contain_text("NavCam framerate: acknowledged", timeout=10_000)
    for name in ("diagnostics", "battery monitor"):
        toggle = page.get_by_role("button", name=name)
        pressed = await toggle.get_attribute("aria-pressed") == "true"
        await toggle.click()
        await expect(answer).to_contain_text(f"{name}: acknowledged", timeout=10_000)
        await expect(toggle).to_have_attribute("aria-pressed", str(not pressed).lower())

    # Switch to the other platform without disconnecting the first.
    await page.locator('#platforms tr[data-platform="rover-2"] button.connect').click()
    await expect(page.get_by_label("NavCam rover-2")).to_be_visible(timeout=10_000)
    await frames_decoded(page, at_least=10)
    assert {"web-rover", "rover-2"} <= set(station.ctx.connections)
    await expect(page.locator("#driving")).to_have_text("not driving")
    assert other.bus.last(topics.OVERRIDE_STATE) is None or not (
        other.bus.last(topics.OVERRIDE_STATE).engaged
    )

    # Its patrol: the area map and route from the platform (the --sim demo field: a
    # boundary, a shed to keep out of, a loop of five points) drawn on the map.
    await expect(page.locator("#map path.area-boundary")).to_have_count(1, timeout=10_000)
    await expect(page.locator("#map path.area-keepout")).to_have_count(1)
    await expect(page.locator("#map path.route-line")).to_have_count(1)
    shown = await station.ctx.api.call_local("map_get", platform_id="rover-2")
    assert len(shown["route"]) == 5
    # Start it from the panel: patrolling along a planned path, and it moves.
    patrol_state = page.locator("#patrol-state")
    patrol_answer = page.locator("#patrol-answer")
    start = await telemetry_position(station, "rover-2")
    await page.get_by_role("button", name="start patrol").click()
    await page.get_by_label("slide to confirm start patrol").fill("100")  # issue 31
    await expect(patrol_state).to_have_attribute("data-state", "patrolling", timeout=10_000)
    await expect(patrol_state).to_contain_text("→ waypoint")
    await expect(page.locator("#map path.planned-path")).to_have_count(1, timeout=10_000)
    await wait_moved(station, "rover-2", start)
    # Edit the route on the map: delete its closing waypoint (the fifth, over the first),
    # then the first; send it; the platform has it.
    await page.get_by_role("button", name="edit route").click()
    await page.locator('#map [title="waypoint 5"]').click(button="right")
    await expect(page.locator('#map [title="waypoint 5"]')).to_have_count(0)
    await page.locator('#map [title="waypoint 1"]').click(button="right")
    await expect(page.locator('#map [title="waypoint 4"]')).to_have_count(0)
    await page.get_by_role("button", name="send route").click()
    await expect(patrol_answer).to_contain_text("route sent: 3 waypoints", timeout=10_000)
    sent = await station.ctx.api.call_local("patrol_get", platform_id="rover-2")
    assert sent["waypoints"] == 3
    routed = (await station.ctx.api.call_local("map_get", platform_id="rover-2"))["route"]
    kept = shown["route"][1:4]
    assert [(w["lat"], w["lon"]) for w in routed] == pytest.approx(
        [(w["lat"], w["lon"]) for w in kept]
    )
    await expect(page.get_by_role("button", name="send route")).to_be_hidden()
    await expect(patrol_state).to_contain_text("→ waypoint 1/3", timeout=10_000)
    await expect(page.locator("#map path.planned-path")).to_have_count(1, timeout=10_000)
    if os.environ.get("BRASIDAS_SCREENSHOT") == "1":
        SCREENSHOT.parent.mkdir(exist_ok=True)
        await page.screenshot(path=str(SCREENSHOT))
    await page.screenshot(path=str(tmp_path / "console.png"))
    # A waypoint outside the boundary (the map's far corner): refused with the reason,
    # the platform's route unchanged, the edit still open; cancel it.
    await page.get_by_role("button", name="edit route").click()
    box = await page.locator("#map").bounding_box()
    assert box is not None
    await page.mouse.click(box["x"] + box["width"] - 6, box["y"] + box["height"] - 6)
    await expect(page.locator('#map [title="waypoint 4"]')).to_have_count(1)
    await page.get_by_role("button", name="send route").click()
    await expect(patrol_answer).to_contain_text("send route: waypoints refused:", timeout=10_000)
    await expect(patrol_answer).to_contain_text("outside")
    sent = await station.ctx.api.call_local("patrol_get", platform_id="rover-2")
    assert sent["waypoints"] == 3
    await page.get_by_role("button", name="cancel route edit").click()
    await expect(page.locator('#map [title="waypoint 1"]')).to_have_count(0)
    await keep_out_zones_drawn_and_removed(page, station, "rover-2")
    # Another station takes control (--force): this console says so (the 90.17
    # notification, at once or with the next heartbeat's answer), by whom, and its stop
    # is refused, by whom said.
    authority = page.get_by_label("command authority")
    intruder = PlatformConnection(
        "rover-2", other.ctx.signaling_url, station_id="intruder", fleet_key=fleet_key
    )
    await intruder.open()
    try:
        taken = await intruder.call(
            "issue_system_command", group=10, command=0, payload="state=True,force=yes"
        )
        assert taken["accepted"], taken
        await expect(authority).to_have_attribute("data-state", "taken", timeout=20_000)
        await expect(authority).to_contain_text("CONTROL TAKEN by station intruder")
        # An observer's map is read-only: no drawing, no removing.
        draw_keepout = page.get_by_role("button", name="draw keep-out")
        await expect(draw_keepout).to_be_disabled()
        await expect(draw_keepout).to_have_attribute("title", re.compile("intruder"))
        await expect(page.get_by_role("button", name="remove keep-out shed")).to_be_disabled()
        # Its patrol controls are disabled before any click (issue 20), saying why.
        stop_patrol = page.get_by_role("button", name="stop patrol")
        await expect(stop_patrol).to_be_disabled()
        await expect(stop_patrol).to_have_attribute("title", re.compile("intruder"))
        # The intruder's link goes silent (its heartbeats stop): after failsafe.hold_after
        # (1.5 s) the platform holds, and the page shows LINK LOST.
        assert intruder._heartbeat is not None
        intruder._heartbeat.cancel()
        banner = page.get_by_role("alert", name="failsafe")
        await expect(banner).to_contain_text("LINK LOST — platform on HOLD", timeout=10_000)
        # Take control back, confirmed in the page: this console drives, the hold ends
        # and the intruder is told it observes.
        await page.get_by_role("button", name="take control").click()
        confirm = page.get_by_role("group", name="confirm takeover")
        await expect(confirm).to_contain_text("take control from station intruder?")
        assert other.ctx.authority.station_id == "intruder"  # nothing sent unconfirmed
        await confirm.get_by_role("button", name="confirm take control").click()
        await expect(page.locator("#driving")).to_have_text(
            "this console is driving rover-2", timeout=10_000
        )
        await expect(authority).to_have_attribute("data-state", "driving")
        await expect(draw_keepout).to_be_enabled()
        await expect(banner).to_be_hidden(timeout=10_000)
        assert other.ctx.authority.station_id == station.config.station.id
        answer_to_intruder = await intruder.call("heartbeat")
        assert answer_to_intruder["control"] is False
        assert answer_to_intruder["controller"] == station.config.station.id
        # The speed cap for the latency this station reports, near the override.
        cap = page.get_by_label("speed cap")
        await expect(cap).to_have_text(re.compile(r"^cap \d+\.\d km/h \(video "))
        assert float(await cap.get_attribute("data-kmh") or "nan") > 0
        # Its turret (the simulated microcontroller): safe, where it points.
        turret = page.get_by_label("turret", exact=True)
        await expect(turret).to_contain_text("trigger safe", timeout=10_000)
        await expect(turret).to_contain_text("azimuth")
        await expect(turret).to_have_attribute("data-trigger", "safe")
    finally:
        await intruder.close()
    await page.get_by_role("button", name="stop patrol").click()
    await expect(patrol_state).to_have_attribute("data-state", "stopped", timeout=10_000)

    # Back to the first and disconnect: it returns to Autonomous Mode.
    await page.locator('#platforms tr[data-platform="web-rover"] button.connect').click()
    await expect(page.locator("#disconnect")).to_be_visible(timeout=10_000)
    await page.locator("#disconnect").click()
    await wait_until(lambda: not rover.bus.last(topics.OVERRIDE_STATE).engaged)
    assert rover.bus.last(topics.OVERRIDE_STATE).mode.value == "autonomous"
    await wait_until(lambda: "web-rover" not in station.ctx.connections)
    assert errors == []


async def test_warnings_audio_link_loss_and_a_closed_page_stops_the_robot(
    platform_factory: Factory, fleet_key: bytes, browser: Any
) -> None:
    """A group 90 warning (low battery: the simulated pack's 24.7 V is under a 30 V limit)
    flashes until the operator acknowledges it. The platform's microphone is decoded in the
    page, and push-to-talk reaches the platform's speaker. The link to the platform is cut
    while driving: LINK LOST, the platform holds; restored: the page asks for a re-engage and
    the robot does not move until the operator re-engages from the page. Then the station's
    safety net: the page's socket closes while a key is held, with no JavaScript left to send
    a stop."""
    from playwright.async_api import expect

    async with (
        running_station(
            fleet_key, "telemetry.battery_low_v=30", "telemetry.battery_clear_v=31"
        ) as station,
    ):
        rover = await sim_platform(
            platform_factory,
            fleet_key,
            station,
            "web-rover",
            23.6530,
            FRAMES_COUNTED,
            "failsafe.hold_after=0.6",
            # Holding until the operator re-engages (no release, the session outlives the cut).
            "failsafe.release_after=60",
            "signaling.session_timeout=60",
        )
        page = await browser.new_page()
        await page.goto(f"http://127.0.0.1:{station.api_port}/?platform=web-rover")
        warning = page.locator("#annunciator button.warning", has_text="web-rover")
        await expect(warning).to_have_class(re.compile("unacknowledged"), timeout=10_000)
        await expect(warning).to_have_attribute("aria-pressed", "false")
        await warning.click()
        await expect(warning).to_have_attribute("aria-pressed", "true")
        await expect(warning).not_to_have_class(re.compile("unacknowledged"))

        listen = page.get_by_role("button", name="listen")
        await listen.click()
        await expect(listen).to_have_attribute("aria-pressed", "true")
        await expect(listen).to_have_attribute(
            "data-decoded", re.compile(r"^([2-9]\d|\d{3,})$"), timeout=10_000
        )  # 20 packets of 20 ms decoded in the page
        speaker = rover.ctx.media.streams["audio_in"]
        await page.locator("#talk").hover()
        await page.mouse.down()
        await wait_until(lambda: speaker.hears_sound, timeout=10)
        await page.mouse.up()
        await expect(page.locator("#talk")).to_have_attribute("aria-pressed", "false")
        await wait_until(lambda: speaker.state.value == "idle", timeout=15)

        # The page's socket drops: it says so, reconnects, and the picture comes back.
        decoded = await frames_decoded(page, at_least=1)
        await page.evaluate("window.navcam.dropStationConnection()")
        states: list[str] = []
        async with asyncio.timeout(10):  # the close is seen, then the new socket opens
            while states[-2:] != ["reconnecting", "connected"]:
                await asyncio.sleep(0.05)
                states = await page.evaluate("window.navcam.apiStates")
        await expect(page.locator("#api-state")).to_have_text("station connected")
        await frames_decoded(page, at_least=decoded + 10)

        override = page.get_by_role("button", name="manual override")
        await override.click()
        await expect(override).to_have_attribute("aria-pressed", "true", timeout=10_000)
        vehicle = rover.ctx.sim.vehicle
        assert vehicle is not None
        await page.keyboard.down("KeyW")
        await wait_until(lambda: vehicle.command[0] > 0.3, timeout=15)

        # The link is cut while driving: the motors stop (the platform's deadman), the page
        # says LINK LOST (no telemetry), the platform holds (no heartbeat).
        cut = LinkCut(station, "web-rover")
        cut.cut()
        try:
            banner = page.get_by_role("alert", name="failsafe")
            await wait_until(lambda: vehicle.command == (0.0, 0.0), timeout=15)
            await expect(banner).to_contain_text("LINK LOST", timeout=15_000)
            await wait_until(
                lambda: rover.bus.last(topics.FAILSAFE_STATE).step is FailsafeStep.HOLD,
                timeout=10,
            )
            await page.keyboard.up("KeyW")
        finally:
            cut.restore()
        # The link is back: the page shows the hold and asks for a deliberate re-engage.
        await expect(banner).to_have_attribute("data-step", "rejoin", timeout=15_000)
        await expect(banner).to_contain_text("LINK LOST — platform on HOLD")
        await expect(banner).to_contain_text("re-engage the override to drive")
        await expect(override).to_have_text("override: HOLD — press to re-engage")
        # W held again: its velocities reach the platform and are dropped (held).
        held = velocities_dropped(rover, "held")
        await page.keyboard.down("KeyW")
        await wait_until(lambda: velocities_dropped(rover, "held") >= held + 10, timeout=10)
        assert vehicle.command == (0.0, 0.0), "moved before the operator re-engaged"
        await page.keyboard.up("KeyW")
        # The operator re-engages from the page: the hold ends, and W drives again.
        await override.click()
        await expect(override).to_have_text("override: ENGAGED", timeout=10_000)
        await expect(banner).to_be_hidden(timeout=10_000)
        assert rover.bus.last(topics.FAILSAFE_STATE).step is FailsafeStep.NORMAL
        await page.keyboard.down("KeyW")
        await wait_until(lambda: vehicle.command[0] > 0.3, timeout=15)
        await page.close(run_before_unload=False)
        await wait_until(lambda: vehicle.command == (0.0, 0.0), timeout=2)


async def test_a_remote_operator_needs_https_and_gets_video_over_it(
    platform_factory: Factory, fleet_key: bytes, tmp_path: Path, browser: Any
) -> None:
    """Plain HTTP by a host name is no secure context: the page says why there is no video.
    The HTTPS console (console.tls_cert) by a configured name decodes the NavCam."""
    from playwright.async_api import expect

    cert, key = tmp_path / "cert.pem", tmp_path / "key.pem"
    openssl = await asyncio.create_subprocess_exec(
        "openssl", "req", "-x509", "-newkey", "ec", "-pkeyopt", "ec_paramgen_curve:P-256",
        "-nodes", "-days", "1", "-subj", "/CN=station.test", "-keyout", str(key),
        "-out", str(cert), stdout=asyncio.subprocess.DEVNULL, stderr=asyncio.subprocess.DEVNULL,
    )  # fmt: skip
    assert await openssl.wait() == 0
    async with running_station(
        fleet_key,
        f"console.tls_cert={cert}",
        f"console.tls_key={key}",
        "console.https_host=127.0.0.1",
        "console.https_port=0",
        'console.https_names=["station.test"]',
    ) as daemon:
        await sim_platform(platform_factory, fleet_key, daemon, "web-rover", 23.6530)
        context = await browser.new_context(ignore_https_errors=True)
        page = await context.new_page()
        await page.goto(f"http://station.test:{daemon.api_port}/")
        await expect(page.locator("#video-message")).to_contain_text("not a secure context")
        await page.goto(f"https://station.test:{daemon.console_https_port}/?platform=web-rover")
        await expect(page.locator("#api-state")).to_have_text("station connected")
        await frames_decoded(page, at_least=5)
        # Closed by the browser first: a station stopping under open TLS connections leaves
        # their shutdown timers (30 s each) on the loop.
        await context.close()
