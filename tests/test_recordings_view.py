"""The console's recordings view (issue 23) in headless Chromium: a --sim platform's recording
is listed, opened (the station fetches it) and replayed; seeking to a time shows that time's
position on the map and that time's NavCam frame."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import os
import re
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from conftest import free_udp_port, quiet_platform_config, running_station, wait_until
from mcap.reader import make_reader
from support.cli import run_cli
from support.console import SETTLED_JS

from brasidas import topics
from platformd.app import PlatformDaemon
from stationd.api_client import api_call_async

Factory = Callable[..., Awaitable[PlatformDaemon]]
DOCS = Path(__file__).resolve().parent.parent / "docs"


def finished_with_video(directory: Path) -> list[Path]:
    found = []
    for path in sorted(directory.glob("*.mcap")):
        with open(path, "rb") as stream:
            summary = make_reader(stream).get_summary()
        if summary is not None and any(c.topic == "/navcam" for c in summary.channels.values()):
            found.append(path)
    return found


def expected_at(path: Path, fraction: float) -> dict[str, Any]:
    """The time at ``fraction`` of the file, the position then and the frame shown then."""
    with open(path, "rb") as stream:
        reader = make_reader(stream)
        stats = reader.get_summary().statistics  # type: ignore[union-attr]
        assert stats is not None
        at = stats.message_start_time + int(
            (stats.message_end_time - stats.message_start_time) * fraction
        )
        pose = frame = None
        for _s, channel, message in reader.iter_messages(ending_at=at):
            if channel.topic == "/pose":
                pose = (message.log_time, json.loads(message.data))
            elif channel.topic == "/navcam":
                frame = message.log_time
    assert pose is not None
    assert frame is not None
    return {"at": at, "start": stats.message_start_time, "pose": pose, "frame": frame}


def with_video_gap(path: Path, out: Path, fraction: float) -> int:
    """A copy of ``path`` whose NavCam stops at ``fraction`` of the file while telemetry goes
    on (a stream paused mid-recording); returns the time the video stops."""
    from mcap.writer import Writer

    with open(path, "rb") as source, open(out, "wb") as sink:
        reader = make_reader(source)
        stats = reader.get_summary().statistics  # type: ignore[union-attr]
        assert stats is not None
        stop = stats.message_start_time + int(
            (stats.message_end_time - stats.message_start_time) * fraction
        )
        writer = Writer(sink)
        writer.start(profile="", library="test")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=True):
            if channel.topic == "/navcam" and message.log_time >= stop:
                continue
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(
                    channel.topic,
                    channel.message_encoding,
                    schemas.get(channel.schema_id, 0),
                    dict(channel.metadata),
                )
            writer.add_message(
                channels[channel.id], message.log_time, message.data, message.publish_time
            )
        writer.finish()  # type: ignore[no-untyped-call]
    return stop


async def test_seeking_shows_that_times_position_and_frame(
    platform_factory: Factory, fleet_key: bytes, tmp_path: Path, browser: Any
) -> None:
    from playwright.async_api import expect

    recordings = tmp_path / "recordings"
    platform = await platform_factory(
        quiet_platform_config(
            "platform.id=rover-rp",
            "sim.enabled=true",
            "gps.enabled=true",
            "navcam.enabled=true",
            "recorder.enabled=true",
            f"recorder.dir={recordings}",
            "recorder.rotate_minutes=0.1",  # 6 s files: the first, finished, is the one seen
            f"map.file={tmp_path / 'map.geojson'}",
            f"autonomy.route_file={tmp_path / 'route.json'}",
        ),
        fleet_key,
    )
    async with running_station(fleet_key) as station:
        code, _, err = await run_cli(
            station, "connect", "rover-rp", "--url", platform.ctx.signaling_url
        )
        assert code == 0, err
        port = str(free_udp_port())
        code, _, err = await run_cli(
            station, "stream", "rover-rp", "navcam", "start", "--port", port
        )
        assert code == 0, err

        async def recorded() -> bool:
            return bool(await asyncio.to_thread(finished_with_video, recordings))

        deadline = asyncio.get_running_loop().time() + 60
        while not await recorded():
            assert asyncio.get_running_loop().time() < deadline, "no finished recording"
            await asyncio.sleep(0.5)
        path = (await asyncio.to_thread(finished_with_video, recordings))[0]
        expected = await asyncio.to_thread(expected_at, path, 0.7)

        page = await browser.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda error: errors.append(str(error)))
        await page.goto(f"http://127.0.0.1:{station.api_port}/")
        await page.locator("#recordings-toggle").click()
        await page.locator("#rec-platform").fill("rover-rp")
        await page.locator("#rec-list-button").click()
        option = page.locator(f'#rec-list option[value="{path.name}"]')
        await expect(option).to_have_count(1, timeout=15_000)
        await page.locator("#rec-list").select_option(path.name)
        await page.locator("#rec-open").click()
        view = page.locator("#recordings")
        await expect(view).to_have_attribute("data-recording", path.name, timeout=30_000)

        seconds = (expected["at"] - expected["start"]) / 1e9
        await page.evaluate(
            """(seconds) => {
                const slider = document.getElementById("rec-time");
                slider.value = String(seconds);
                slider.dispatchEvent(new Event("input"));
            }""",
            seconds,
        )
        pose_time, pose = expected["pose"]

        async def shown(selector: str, attribute: str) -> float:
            value = await page.locator(selector).get_attribute(attribute)
            return float(value) if value else 0.0

        async def in_step() -> bool:
            position_ns = await shown("#rec-position", "data-time-ns")
            frame_ns = await shown("#rec-video", "data-frame-time-ns")
            return abs(position_ns - pose_time) < 2000 and abs(frame_ns - expected["frame"]) < 2000

        deadline = asyncio.get_running_loop().time() + 20
        while not await in_step():
            assert asyncio.get_running_loop().time() < deadline, (
                await page.locator("#rec-position").get_attribute("data-time-ns"),
                await page.locator("#rec-video").get_attribute("data-frame-time-ns"),
                pose_time,
                expected["frame"],
                await page.locator("#rec-message").text_content(),
            )
            await asyncio.sleep(0.2)
        lat = float(await page.locator("#rec-position").get_attribute("data-lat") or 0)
        lon = float(await page.locator("#rec-position").get_attribute("data-lon") or 0)
        assert abs(lat - pose["latitude"]) < 1e-9
        assert abs(lon - pose["longitude"]) < 1e-9
        await expect(page.locator("#rec-position")).to_contain_text(f"{lat:.6f}")
        # The frame was drawn: the canvas holds a picture, not the empty black.
        lit = await page.evaluate(
            """() => {
                const c = document.getElementById("rec-video");
                const d = c.getContext("2d").getImageData(0, 0, c.width, c.height).data;
                let lit = 0;
                for (let i = 0; i < d.length; i += 4 * 13) if (d[i] + d[i + 1] + d[i + 2] > 60) lit++;
                return lit;
            }"""
        )
        assert lit > 50  # the ball and the clock overlays on black
        # The plots' cursor is at that time.
        cursor = float(await page.locator("#rec-plot").get_attribute("data-cursor-ns") or 0)
        assert abs(cursor - expected["at"]) < 2000
        # The marker on the map is at that position.
        assert await page.locator("#rec-map path.leaflet-interactive").count() >= 2
        marker = await page.locator("#rec-map").get_attribute("data-marker")
        assert marker is not None
        shown_at = [float(part) for part in marker.split(",")]
        assert abs(shown_at[0] - lat) < 1e-9
        assert abs(shown_at[1] - lon) < 1e-9
        no_video = page.get_by_role("alert", name="no recorded video")
        await expect(no_video).to_be_hidden()  # the frame of that moment

        # Issue 31: seeking into a stretch without video left the previous frame up,
        # unmarked. The picture now says it is not of this moment.
        gap = recordings / f"gap-{path.name}"
        await asyncio.to_thread(with_video_gap, path, gap, 0.3)
        await page.locator("#rec-list-button").click()
        option = page.locator(f'#rec-list option[value="{gap.name}"]')
        await expect(option).to_have_count(1, timeout=15_000)
        await page.locator("#rec-list").select_option(gap.name)
        await page.locator("#rec-open").click()
        await expect(view).to_have_attribute("data-recording", gap.name, timeout=30_000)
        # Before the video stops and 1.8 s or more after it (NO_VIDEO_AFTER_NS is 1 s).
        for fraction, marked in ((0.2, False), (0.95, True), (0.2, False), (0.6, True)):
            await page.evaluate(
                """(seconds) => {
                    const slider = document.getElementById("rec-time");
                    slider.value = String(seconds);
                    slider.dispatchEvent(new Event("input"));
                }""",
                (expected["at"] - expected["start"]) / 1e9 / 0.7 * fraction,
            )
            if marked:
                await expect(no_video).to_be_visible(timeout=10_000)
                await expect(no_video).to_contain_text("NO VIDEO at this time")
            else:
                await expect(no_video).to_be_hidden(timeout=10_000)

        # The same dark theme and units as the live view, everything above the fold.
        background = await view.evaluate("(e) => getComputedStyle(e).backgroundColor")
        assert background == "rgb(21, 26, 32)", background
        rows = page.locator("#rec-instruments")
        await expect(rows).to_contain_text(re.compile(r"\d+\.\d km/h"))
        await expect(rows).not_to_contain_text(re.compile(r"\d\.\d{4,}"))
        for width, height in ((1366, 768), (1920, 1080)):
            await page.set_viewport_size({"width": width, "height": height})
            await page.evaluate(SETTLED_JS)  # the resize handlers and observers have run
            for part in ("#rec-instruments", "#rec-log", "#rec-plot", "#rec-map"):
                box = await page.locator(part).bounding_box()
                assert box is not None, (part, box)
                assert box["y"] + box["height"] <= height, (part, box)
            if os.environ.get("BRASIDAS_SCREENSHOT") == "1":
                await page.screenshot(path=str(DOCS / f"recordings-{width}x{height}.png"))
        assert not errors, errors


def small_recording(path: Path, payload_bytes: int) -> None:
    """A finished MCAP file of about ``payload_bytes`` (one incompressible log message)."""
    from mcap.writer import CompressionType, Writer

    with open(path, "wb") as stream:
        writer = Writer(stream, compression=CompressionType.NONE)
        writer.start(profile="", library="test")
        schema = writer.register_schema("foxglove.Log", "jsonschema", b"{}")
        channel = writer.register_channel("/log", "json", schema)
        writer.add_message(channel, 1_000, os.urandom(payload_bytes), 1_000)
        writer.finish()  # type: ignore[no-untyped-call]


async def test_the_replay_cache_keeps_within_its_quota_least_recently_opened_first(
    platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    recordings = tmp_path / "recordings"
    recordings.mkdir()
    names = [f"2026112{n}T000000.000Z-rover-rc.mcap" for n in range(4)]
    for name in names:
        small_recording(recordings / name, 400_000)
    platform = await platform_factory(
        quiet_platform_config(
            "platform.id=rover-rc", "recorder.enabled=true", f"recorder.dir={recordings}"
        ),
        fleet_key,
    )
    async with running_station(fleet_key, f"replay.max_bytes={1024 * 1024}") as station:
        code, _, err = await run_cli(
            station, "connect", "rover-rc", "--url", platform.ctx.signaling_url
        )
        assert code == 0, err
        cache = tmp_path / "state" / "brasidas" / "replay" / "rover-rc"
        config = dataclasses.replace(
            station.ctx.config,
            station=dataclasses.replace(station.ctx.config.station, api_port=station.api_port),
        )

        async def open_(name: str) -> set[str]:
            answer = await api_call_async(
                config, "recording_open", platform_id="rover-rc", name=name
            )
            assert answer["channels"]["/log"]["messages"] == 1
            return {p.name for p in cache.iterdir()}

        a, b, c, d = names
        assert await open_(a) == {a}
        assert await open_(b) == {a, b}
        assert await open_(c) == {b, c}  # 1.2 MB > 1 MiB: the oldest goes
        await asyncio.sleep(0.02)  # a later mtime than c's, on any file system's clock
        assert await open_(b) == {b, c}  # cached: opened again, now the most recent
        assert await open_(d) == {b, d}  # c is now the least recently opened
        assert sum(p.stat().st_size for p in cache.iterdir()) <= 1024 * 1024


def video_times(path: Path) -> list[int]:
    with open(path, "rb") as stream:
        return [m.log_time for _s, _c, m in make_reader(stream).iter_messages(topics=["/navcam"])]


def summary_start(path: Path) -> int:
    with open(path, "rb") as stream:
        stats = make_reader(stream).get_summary().statistics  # type: ignore[union-attr]
    assert stats is not None
    return int(stats.message_start_time)


def fast_recording(directory: Path) -> Path | None:
    """A finished recording whose NavCam ran at 30 fps (the override engaged) for most of it."""
    for path in finished_with_video(directory):
        times = video_times(path)
        if len(times) > 60 and len(times) / ((times[-1] - times[0]) / 1e9) > 20:
            return path
    return None


async def test_playing_at_1x_shows_every_recorded_frame(
    platform_factory: Factory, fleet_key: bytes, tmp_path: Path, browser: Any
) -> None:
    """Not 4 frames a second (the timeline's ticks): every access unit recorded, at its rate."""
    from playwright.async_api import expect

    recordings = tmp_path / "recordings"
    platform = await platform_factory(
        quiet_platform_config(
            "platform.id=rover-fps",
            "sim.enabled=true",
            "navcam.enabled=true",
            "motor.enabled=true",
            "recorder.enabled=true",
            f"recorder.dir={recordings}",
            "recorder.rotate_minutes=0.1",
        ),
        fleet_key,
    )
    async with running_station(fleet_key) as station:
        code, _, err = await run_cli(
            station, "connect", "rover-fps", "--url", platform.ctx.signaling_url
        )
        assert code == 0, err
        code, _, err = await run_cli(
            station, "stream", "rover-fps", "navcam", "start", "--port", str(free_udp_port())
        )
        assert code == 0, err
        controller = topics.CONTROLLER_STATUS
        await wait_until(lambda: getattr(platform.bus.last(controller), "connected", False), 20)
        code, out, err = await run_cli(station, "movrd", "rover-fps", "on")  # 30 fps
        assert code == 0, out + err
        deadline = asyncio.get_running_loop().time() + 90
        while (path := await asyncio.to_thread(fast_recording, recordings)) is None:
            assert asyncio.get_running_loop().time() < deadline, "no 30 fps recording"
            await asyncio.sleep(0.5)
        times = await asyncio.to_thread(video_times, path)
        start = await asyncio.to_thread(summary_start, path)

        page = await browser.new_page()
        errors: list[str] = []
        page.on("pageerror", lambda error: errors.append(str(error)))
        await page.goto(f"http://127.0.0.1:{station.api_port}/")
        await page.locator("#recordings-toggle").click()
        await page.locator("#rec-platform").fill("rover-fps")
        await page.locator("#rec-list-button").click()
        option = page.locator(f'#rec-list option[value="{path.name}"]')
        await expect(option).to_have_count(1, timeout=15_000)
        await page.locator("#rec-list").select_option(path.name)
        await page.locator("#rec-open").click()
        view = page.locator("#recordings")
        await expect(view).to_have_attribute("data-recording", path.name, timeout=30_000)
        # From a second after the first frame, at 1x.
        await page.evaluate(
            """(seconds) => {
                const slider = document.getElementById("rec-time");
                slider.value = String(seconds);
                slider.dispatchEvent(new Event("input"));
            }""",
            (times[0] - start) / 1e9 + 1.0,
        )
        await page.locator("#rec-play").click()

        async def sample() -> tuple[int, int]:
            """Frames drawn so far and the last one's time, read at one moment."""
            drawn, at = await page.evaluate(
                """() => {
                    const c = document.getElementById("rec-video");
                    return [c.dataset.framesDrawn || "0", c.dataset.frameTimeNs || "0"];
                }"""
            )
            return int(drawn), int(at)

        await asyncio.sleep(1.5)  # playing steadily
        drawn_0, at_0 = await sample()
        await asyncio.sleep(1.5)
        drawn_1, at_1 = await sample()
        message = await page.locator("#rec-message").text_content()
        assert not errors, errors
    played_s = (at_1 - at_0) / 1e9
    # The page holds times as JavaScript numbers (doubles: 256 ns steps at today's epoch
    # nanoseconds), so the last frame drawn can read up to 128 ns before its recorded time:
    # compared as integers it fell outside (at_0, at_1] and one drawn frame more than recorded
    # was counted. Compare at the page's precision.
    recorded = sum(1 for t in times if float(at_0) < float(t) <= float(at_1))
    drawn = drawn_1 - drawn_0
    assert played_s > 0.5, (at_0, at_1, message)
    assert recorded / played_s > 20, (recorded, played_s)
    # Every one, but for a frame or two of a tick that came too late under load (the old
    # player drew one a tick: 6 here); never more: the frames come up in their order, and the
    # time shown is the recorded one (not rounded to the decoder's microseconds).
    assert 0.9 * recorded <= drawn, (drawn, recorded, played_s, message)
    assert drawn <= recorded, (drawn, recorded, played_s, message)


def test_a_tick_of_play_gets_the_units_after_the_decoders_last_across_a_keyframe(
    tmp_path: Path,
) -> None:
    """30 fps, a keyframe every 10 units: at a tick, the units after the last one the
    decoder had (keyframes or not), not only those from the latest keyframe."""
    from mcap.writer import CompressionType, Writer

    from brasidas.recording import schemas
    from stationd.replay import recording_state

    path = tmp_path / "video.mcap"
    start, step = 1_000_000_000_000, 33_333_333
    with open(path, "wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="", library="test")
        schema = writer.register_schema("foxglove.CompressedVideo", "jsonschema", b"{}")
        channel = writer.register_channel("/navcam", "json", schema)
        for i in range(60):
            nal = b"\x00\x00\x00\x01\x65" if i % 10 == 0 else b"\x00\x00\x00\x01\x41"
            t = start + i * step
            writer.add_message(channel, t, schemas.encode_video(t, nal + bytes([i])), t)
        writer.finish()  # type: ignore[no-untyped-call]
    at = start + 25 * step
    from_keyframe = recording_state(path, at)
    assert [f["time_ns"] for f in from_keyframe["frames"]] == [
        start + i * step for i in range(20, 26)
    ]
    assert from_keyframe["frames_after_ns"] is None
    after = start + 17 * step
    following = recording_state(path, at, after)
    assert [f["time_ns"] for f in following["frames"]] == [start + i * step for i in range(18, 26)]
    assert following["frames_after_ns"] == after
    # Too far back (past the video window) or ahead: from the keyframe again.
    assert recording_state(path, at, at)["frames_after_ns"] is None
    assert recording_state(path, at, at - 4_000_000_000)["frames_after_ns"] is None
