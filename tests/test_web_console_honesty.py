"""The console tells the truth (issue 20): a frozen picture is marked STALE with the reason and
the way back, two consumers of one station each keep their picture, the page's measured
latency reaches the platform's speed cap, a loaded background keeps the area map, the stale
telemetry timer counts from the last report, a route edit keeps its loop, and an observer's
controls are disabled before the click. Headless Chromium against a --sim platform."""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import socket
import time
from pathlib import Path
from typing import Any

import pytest
from conftest import wait_until
from support.console import (
    FRAMES_COUNTED,
    Factory,
    console,
    frames_decoded,
    rover,
    screenshots,
)

from brasidas import topics
from brasidas.annunciator import LINK_LOST
from brasidas.codecs.jsonrpc import RpcError
from brasidas.messages import StationNotification
from stationd.client import PlatformConnection
from stationd.daemon import StationDaemon


class UdpCatcher:
    """A local UDP port counting what arrives (another consumer of the station's video)."""

    def __init__(self) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.setblocking(False)
        self.port: int = self.sock.getsockname()[1]
        self.received = 0

    def drain(self) -> int:
        while True:
            try:
                self.sock.recv(65536)
            except BlockingIOError:
                return self.received
            self.received += 1

    def close(self) -> None:
        self.sock.close()


async def test_a_frozen_navcam_is_marked_stale_with_its_reason_and_way_back(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, browser: Any
) -> None:
    """`brasidas-station view` takes the station's feed: both keep their picture (it used to
    freeze the page's canvas while the overlay said 9 fps). The platform pauses the stream:
    within a second the picture is STALE, "NO VIDEO n s", fps 0 (never held), the reason
    (paused) and a resume button, which brings the picture back."""
    from playwright.async_api import expect

    # 60 frames are counted below: at 15 fps, not the idle 5, they take 4 s instead of 12.
    await rover(platform_factory, fleet_key, station, "navcam.idle_framerate=15")
    page = await console(browser, station, "web-rover")
    await frames_decoded(page, at_least=10)
    stale = page.get_by_role("alert", name="video stale")
    await expect(stale).to_be_hidden()
    view = UdpCatcher()
    try:
        # What `view ID --sdp x.sdp` asks the station for: the NavCam to another local port.
        await station.ctx.api.call_local(
            "stream_start", platform_id="web-rover", stream="navcam", port=view.port
        )
        decoded = await frames_decoded(page, at_least=1)
        await frames_decoded(page, at_least=decoded + 20)  # the page's picture goes on
        await wait_until(lambda: view.drain() > 20, timeout=10)  # and so does view's
        await expect(stale).to_be_hidden()
        # view ends (Ctrl-C): it stops its own copy only.
        await station.ctx.api.call_local(
            "stream_stop", platform_id="web-rover", stream="navcam", port=view.port
        )
        decoded = await frames_decoded(page, at_least=1)
        await frames_decoded(page, at_least=decoded + 20)
    finally:
        view.close()

    await station.ctx.api.call_local("stream_pause", platform_id="web-rover", stream="navcam")
    await expect(stale).to_be_visible(timeout=5_000)
    await expect(stale).to_contain_text(re.compile(r"NO VIDEO \d+\.\d s"))
    await expect(page.locator("#video-box")).to_have_attribute("data-stale", "true")
    await expect(page.get_by_label("frame rate")).to_have_text("0 fps", timeout=5_000)
    await expect(page.get_by_label("glass-to-glass latency")).to_have_text("—")
    await expect(page.get_by_label("video age")).to_have_text(re.compile(r"^\d+\.\d s$"))
    await expect(stale).to_contain_text("paused", timeout=10_000)
    decoded = await frames_decoded(page, at_least=1)
    await page.get_by_role("button", name="resume video").click()
    await frames_decoded(page, at_least=decoded + 10)
    await expect(stale).to_be_hidden(timeout=5_000)
    await expect(page.get_by_label("frame rate")).to_have_text(re.compile(r"^[1-9]\d* fps$"))


async def test_the_pages_latency_reaches_the_speed_cap(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, browser: Any
) -> None:
    """The console holding the override: the platform's cap follows the page's measured
    glass-to-glass (it used to stay at the 400 ms assumption). The video freezes: the picture's
    age counts, and the cap falls below the assumption's."""
    from playwright.async_api import expect

    platform = await rover(
        platform_factory, fleet_key, station, "safety.report_max_age_s=1.5", FRAMES_COUNTED
    )
    page = await console(browser, station, "web-rover")
    await frames_decoded(page, at_least=10)
    override = page.get_by_role("button", name="manual override")
    await override.click()
    await expect(override).to_have_attribute("aria-pressed", "true", timeout=10_000)

    def cap_video_ms() -> float | None:
        cap = platform.bus.last(topics.SPEED_CAP)
        return None if cap is None else cap.video_ms

    await wait_until(lambda: cap_video_ms() is not None, timeout=10)
    # Rolling plots (uPlot, served from node_modules): battery and glass-to-glass by default.
    await expect(page.locator("#plots .uplot")).to_have_count(2, timeout=10_000)
    await page.get_by_role("checkbox", name="motor A").check()
    await expect(page.locator("#plots .uplot")).to_have_count(3, timeout=5_000)
    await page.keyboard.down("KeyW")  # the command sent, on the stick
    await screenshots(page, "console")
    swap = page.get_by_role("button", name="swap map and video")
    await swap.click()  # the map takes the main area, the NavCam a picture-in-picture
    await expect(page.locator("#video-pane > #map")).to_have_count(1)
    await expect(page.locator("#video-box")).to_have_css("position", "fixed")
    await screenshots(page, "console-map")
    await swap.click()
    await expect(page.locator("#side > #map")).to_have_count(1)
    await expect(page.locator("#video-box")).to_have_css("position", "relative")
    await page.keyboard.up("KeyW")
    # The measured glass-to-glass, not the assumption (None). How low it is, is the bench's
    # (`make bench console`): on a starved CPU it passed 400 ms and this test failed.
    await wait_until(lambda: (cap_video_ms() or 0) > 0, timeout=10)
    playing_ms = cap_video_ms() or 0.0
    readout = page.get_by_label("speed cap", exact=True)
    reason = page.get_by_label("why this cap")  # in plain sight, not a tooltip
    await expect(readout).to_contain_text(re.compile(r"video \d+ ms"), timeout=5_000)
    await expect(reason).not_to_contain_text("no latency report")
    # The picture freezes (paused): its age is the latency now (issue 28), past the 400 ms
    # assumption and what was measured while it played within a second or two of heartbeats,
    # and the cap falls below its worst case.
    await station.ctx.api.call_local("stream_pause", platform_id="web-rover", stream="navcam")
    frozen_past = max(400.0, playing_ms + 500.0)
    await wait_until(lambda: (cap_video_ms() or 0) > frozen_past, timeout=10)
    await expect(readout).to_contain_text(re.compile(r"video \d{3,} ms"), timeout=5_000)


async def test_a_loaded_background_keeps_the_area_map(
    station: StationDaemon,
    platform_factory: Factory,
    fleet_key: bytes,
    browser: Any,
    tmp_path: Path,
) -> None:
    """The platform's boundary, keep-out and named points stay drawn under an operator's
    GeoJSON or image background, and after *grid only* (they used to vanish)."""
    from playwright.async_api import expect

    await rover(platform_factory, fleet_key, station)
    page = await console(browser, station, "web-rover")
    boundary = page.locator("#map path.area-boundary")
    keepout = page.locator("#map path.area-keepout")
    await expect(boundary).to_have_count(1, timeout=15_000)
    await expect(keepout).to_have_count(1)
    points = await page.locator("#map .area-point").count()
    area = tmp_path / "area.geojson"
    ring = [[23.652, 37.941], [23.655, 37.941], [23.655, 37.943], [23.652, 37.941]]
    area.write_text(
        json.dumps(
            {
                "type": "Feature",
                "properties": {},
                "geometry": {"type": "Polygon", "coordinates": [ring]},
            }
        )
    )
    await page.get_by_text("map files and background").click()  # folded at first
    await page.locator("#map-geojson").set_input_files(str(area))
    await expect(page.locator("#map path.area-background")).to_have_count(1)
    await expect(boundary).to_have_count(1)
    await expect(keepout).to_have_count(1)
    assert await page.locator("#map .area-point").count() == points
    image = tmp_path / "area.png"
    await page.screenshot(path=str(image))
    await page.locator("#map-bounds").fill("37.940,23.651,37.943,23.656")
    await page.locator("#map-image").set_input_files(str(image))
    await expect(page.locator("#map img.area-image")).to_have_count(1)
    await expect(boundary).to_have_count(1)
    await page.locator("#map-clear").click()
    await expect(page.locator("#map img.area-image")).to_have_count(0)
    await expect(boundary).to_have_count(1)
    await expect(keepout).to_have_count(1)


@pytest.mark.parametrize("station_settings", [("telemetry.loss_warn_pct=100",)])
async def test_stale_telemetry_counts_from_the_last_report(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, browser: Any
) -> None:
    """The platform goes silent (its datagrams dropped at the station, as when it is stopped):
    the status counts the silence from its last report and the warning's figure grows (they
    used to say "nothing new for 0.0 s" and "silent for 1.0 s")."""
    from playwright.async_api import expect

    await rover(platform_factory, fleet_key, station)
    page = await console(browser, station, "web-rover")
    status = page.get_by_label("status", exact=True)
    await expect(status).to_contain_text("battery", timeout=15_000)
    (receiver,) = [a for a in station.supervisor.actors if a.name == "telemetry"]
    link = receiver.links["web-rover"]
    link.datagram_received = lambda data, addr: None  # on the instance only
    try:
        await expect(status).to_contain_text(
            re.compile(r"STALE \(nothing new for ([3-9]|\d\d)\.\d s\)"), timeout=15_000
        )
        warning = page.locator("#annunciator button.warning", has_text="telemetry silent")
        await expect(warning).to_contain_text(
            re.compile(r"telemetry silent for ([3-9]|\d\d)\.\d s"), timeout=10_000
        )
        # The station keeps the notifications: a reload shows them, 24-hour time first.
        await page.reload()
        notes = page.locator("#notifications li", has_text="telemetry silent")
        await expect(notes.first).to_be_visible(timeout=10_000)
        await expect(notes.first).to_have_text(re.compile(r"^\d\d:\d\d:\d\d web-rover"))
    finally:
        del link.datagram_received
    await expect(status).not_to_contain_text("STALE", timeout=15_000)
    cleared = page.locator("#notifications li.cleared", has_text="link degraded")
    await expect(cleared.first).to_contain_text("cleared", timeout=10_000)
    # A burst of one note is one line, counted; a severe one is coloured as such.
    for _ in range(8):
        station.bus.publish(
            topics.STATION_NOTIFICATIONS,
            StationNotification(
                LINK_LOST, "web-rover", "link_lost", True, "LINK LOST: platform hold", time.time()
            ),
        )
    burst = page.locator("#notifications li.critical", has_text="LINK LOST: platform hold")
    await expect(burst).to_have_count(1, timeout=10_000)
    await expect(burst).to_contain_text("\u00d78")  # times eight


async def test_a_route_edit_keeps_the_loop_and_counts_from_one(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, browser: Any
) -> None:
    """A waypoint added on the map goes before the closing point: the loop stays closed (it
    used to be appended after it, opening the loop). Waypoints count from 1 everywhere: the
    platform's refusal names the point as the page numbers it."""
    from playwright.async_api import expect

    await rover(platform_factory, fleet_key, station)
    page = await console(browser, station, "web-rover")
    await expect(page.locator("#map path.route-line")).to_have_count(1, timeout=15_000)
    shown = (await station.ctx.api.call_local("map_get", platform_id="web-rover"))["route"]
    assert len(shown) == 5
    assert shown[0] == shown[-1]  # a loop of four points
    await page.get_by_role("button", name="edit route").click()
    markers = page.locator('#map [title^="waypoint "]')
    for _ in range(5):  # a click while the map still settles (fitted to the area) can be lost
        # A point between the first two, inside the field, where nothing drawn over the map
        # takes the click: the robot's name beside its arrow covered the halfway point at
        # some fits (a click on it is the robot's, as an operator's would be). The map's
        # place is read at each try: panels filling in as telemetry arrives move it.
        box = await page.locator("#map").bounding_box()
        assert box is not None
        for share in (0.5, 0.35, 0.65, 0.25, 0.75):
            lat = shown[0]["lat"] + share * (shown[1]["lat"] - shown[0]["lat"])
            lon = shown[0]["lon"] + share * (shown[1]["lon"] - shown[0]["lon"])
            at = await page.evaluate(f"window.navcam.mapPixel({lat}, {lon})")
            x, y = box["x"] + at["x"], box["y"] + at["y"]
            under = await page.evaluate(
                f"(() => {{ const e = document.elementFromPoint({x}, {y});"
                " return e ? `${e.tagName}.${e.getAttribute('class')} ${e.title ?? ''}"
                " ${e.closest('.leaflet-marker-pane') ? 'marker' : 'map'}` : null; })()"
            )
            if under is not None and under.endswith(" map"):
                break
        await page.mouse.click(x, y)
        with contextlib.suppress(AssertionError):
            await expect(markers).to_have_count(6, timeout=2_000)
            break
    assert await markers.count() == 6, f"the clicks at ({x:.0f}, {y:.0f}) hit {under}"
    await page.get_by_role("button", name="send route").click()
    answer = page.locator("#patrol-answer")
    await expect(answer).to_contain_text("route sent: 6 waypoints, closed", timeout=10_000)
    routed = (await station.ctx.api.call_local("map_get", platform_id="web-rover"))["route"]
    assert len(routed) == 6
    assert (routed[0]["lat"], routed[0]["lon"]) == (routed[-1]["lat"], routed[-1]["lon"])
    # A refusal numbers the waypoint as the page does: the map's far corner, outside.
    await page.get_by_role("button", name="edit route").click()
    box = await page.locator("#map").bounding_box()
    assert box is not None
    await page.mouse.click(box["x"] + box["width"] - 6, box["y"] + box["height"] - 6)
    await page.get_by_role("button", name="send route").click()
    await expect(answer).to_contain_text("waypoint 6", timeout=10_000)
    await expect(answer).to_contain_text("outside")


async def test_an_observer_sees_its_controls_disabled(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, browser: Any
) -> None:
    """Another station holds control: override, lights, patrol and route buttons are disabled
    before any click, saying who holds control; *take control* stays enabled. With no
    platform chosen, the controls that would do nothing are hidden."""
    from playwright.async_api import expect

    platform = await rover(
        platform_factory,
        fleet_key,
        station,
        "signaling.session_timeout=60",
        "failsafe.release_after=60",
    )
    page = await console(browser, station, "web-rover")
    override = page.get_by_role("button", name="manual override")
    await expect(override).to_be_enabled(timeout=15_000)
    intruder = PlatformConnection(
        "web-rover", platform.ctx.signaling_url, station_id="intruder", fleet_key=fleet_key
    )
    await intruder.open()
    try:
        taken = await intruder.call(
            "issue_system_command", group=10, command=0, payload="state=True,force=yes"
        )
        assert taken["accepted"], taken
        for name in (
            "manual override",
            "main lights",
            "positional lights",
            "start patrol",
            "stop patrol",
            "edit route",
        ):
            button = page.get_by_role("button", name=name, exact=True)
            await expect(button).to_be_disabled(timeout=15_000)
            await expect(button).to_have_attribute("title", re.compile("intruder"))
        await expect(page.get_by_role("button", name="take control")).to_be_enabled()
        # A drive key says why nothing moves.
        await page.keyboard.press("KeyW")
        await expect(page.locator("#answer")).to_contain_text("intruder", timeout=5_000)
    finally:
        await intruder.close()
    # No platform chosen: nothing that would do nothing is shown.
    idle = await console(browser, station)
    await expect(idle.locator("#platforms tr[data-platform='web-rover']")).to_be_visible(
        timeout=15_000
    )
    for name in ("manual override", "start patrol", "edit route", "main lights"):
        await expect(idle.get_by_role("button", name=name)).to_be_hidden()
    await idle.close()


async def test_page_latency_reports_and_stream_copies_are_checked(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes
) -> None:
    """Bad input gets a clear error: a page's latency that is not a number in range, a sixth
    copy of one stream for one station. A copy's stop leaves the others."""
    import aiohttp

    platform = await rover(platform_factory, fleet_key, station)
    for _ in range(150):  # until its beacon is heard
        heard = await station.ctx.api.call_local("list_platforms")
        if any(entry["id"] == "web-rover" for entry in heard):
            break
        await asyncio.sleep(0.1)
    await station.ctx.api.call_local("connect", platform_id="web-rover")
    url = f"http://127.0.0.1:{station.api_port}/api/rpc/ws"
    async with aiohttp.ClientSession() as http, http.ws_connect(url) as ws:
        answers: dict[int, Any] = {}

        async def call(number: int, method: str, params: str) -> Any:
            """``params`` as JSON text: 1e999 is how a page could send infinity."""
            await ws.send_str(
                f'{{"jsonrpc":"2.0","id":{number},"method":"{method}","params":{params}}}'
            )
            while number not in answers:
                message = await ws.receive_json(timeout=10)
                if "id" in message:
                    answers[message["id"]] = message
            return answers[number]

        assert "result" in await call(1, "console_subscribe", "{}")
        for number, bad in enumerate(("[]", '"12"', "1e999", "-1", "1e9", "true", "null"), 10):
            params = f'{{"platform_id":"web-rover","p95_ms":{bad}}}'
            answer = await call(number, "console_latency", params)
            assert "error" in answer, (bad, answer)
        good = '{"platform_id":"web-rover","p95_ms":9.5}'
        assert (await call(30, "console_latency", good))["result"] is True
        connection = station.ctx.connections["web-rover"]
        assert connection.video_latency is not None
        assert connection.video_latency() == 9.5

    catchers = [UdpCatcher() for _ in range(5)]
    try:
        for catcher in catchers[:4]:
            await station.ctx.api.call_local(
                "stream_start", platform_id="web-rover", stream="navcam", port=catcher.port
            )
        with pytest.raises(RpcError, match="at most 4 copies"):
            await station.ctx.api.call_local(
                "stream_start", platform_id="web-rover", stream="navcam", port=catchers[4].port
            )
        await station.ctx.api.call_local(
            "stream_stop", platform_id="web-rover", stream="navcam", port=catchers[0].port
        )
        media = platform.ctx.media
        assert media is not None
        ports = sorted(port for _host, port in media.viewers["navcam"].values())
        assert ports == sorted(c.port for c in catchers[1:4])
    finally:
        for catcher in catchers:
            catcher.close()


async def test_a_feed_sent_elsewhere_says_so_and_comes_back(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, browser: Any
) -> None:
    """The platform stops sending the console's copy while another consumer's goes on (as an
    older platform did when `view` took the stream): STALE, "taken by another consumer" with
    where it goes, and *ask for the video again* brings it back."""
    from playwright.async_api import expect

    platform = await rover(platform_factory, fleet_key, station, FRAMES_COUNTED)
    page = await console(browser, station, "web-rover")
    await frames_decoded(page, at_least=10)
    view = UdpCatcher()
    try:
        await station.ctx.api.call_local(
            "stream_start", platform_id="web-rover", stream="navcam", port=view.port
        )
        (hub,) = [a for a in station.supervisor.actors if a.name == "console"]
        feed_port = hub.feeds[("web-rover", "navcam")].port
        media = platform.ctx.media
        assert media is not None
        (owner,) = [k for k, (_h, port) in media.viewers["navcam"].items() if port == feed_port]
        await media.stop_stream("navcam", session_id=owner, port=feed_port)
        stale = page.get_by_role("alert", name="video stale")
        await expect(stale).to_be_visible(timeout=5_000)
        await expect(stale).to_contain_text("taken by another consumer", timeout=10_000)
        await expect(stale).to_contain_text(f":{view.port}")
        decoded = await frames_decoded(page, at_least=1)
        await page.get_by_role("button", name="resume video").click()
        await frames_decoded(page, at_least=decoded + 10)
        await expect(stale).to_be_hidden(timeout=5_000)
        assert view.drain() > 0  # the other consumer's copy went on throughout
    finally:
        view.close()
