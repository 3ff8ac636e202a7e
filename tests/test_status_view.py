"""``brasidas-station status ID [--watch]``: the rendering, and the CLI against live daemons."""

from __future__ import annotations

import asyncio
import contextlib
import datetime
import io
import json
import os
import random
import tty
from collections.abc import Awaitable, Callable

from conftest import quiet_platform_config, wait_until
from support.cli import run_cli

from brasidas import topics
from brasidas.codecs.telemetry_schema import (
    SCHEMA_VERSION,
    Attitude,
    Battery,
    Computer,
    Controller,
    Diagnostics,
    Gps,
    Lights,
    Override,
    Section,
    SectionError,
    SectionValue,
    Streams,
    Turret,
    VelocityLink,
    snapshot_to_json,
)
from brasidas.messages import LightsState
from platformd.app import PlatformDaemon
from platformd.sim.gps import NmeaGenerator
from platformd.sim.vehicle import Pose
from stationd import cli
from stationd.daemon import StationDaemon
from stationd.status_view import HOME, frame, render

Factory = Callable[..., Awaitable[PlatformDaemon]]

SECTIONS: dict[type[Section], SectionValue] = {
    Override: Override("teleop", True, "station-1"),
    Lights: Lights(True, False, {"positional": "cannot request GPIO line /dev/gpiochip0:17"}),
    Turret: Turret(True, 20.0, 5.0, True, streams={"payload_camera": "playing"}),
    Battery: Battery(22.6, "low", True, age_ms=420),
    Controller: Controller(True, (35.0, 38.0), (1.0, 1.5), age_ms=420),
    Gps: Gps(fix=True, lat=37.9838096, lon=23.7275388, sats=9, hdop=0.9, age_ms=80),
    Attitude: Attitude(1.5, -0.25, 271.0, age_ms=2600, stale=True),
    Computer: SectionError("OSError: [Errno 5] Input/output error"),
    VelocityLink: VelocityLink(120, {"stale": 2, "forged": 0}),
    Streams: Streams({"navcam": "failed"}),
    Diagnostics: None,
}
REPORT = {
    "platform_id": "rover-1",
    "schema": SCHEMA_VERSION,
    "snapshot": snapshot_to_json(SECTIONS),
    "link": {"received": 50, "loss_pct": 2.0, "silence_s": 0.1, "rejected_total": 1,
             "rejected": {"forged": 1}, "round_trip_ms": 1.25, "error": ""},
    "warnings": [
        {"name": "low_battery", "code": "90.10", "message": "low battery (22.6 V)", "since": 1.0},
        {"name": "stream_failed:navcam", "code": "90.14", "message": "stream navcam failed",
         "since": 1.0},
    ],
}  # fmt: skip


def test_render_shows_every_section_and_names_the_warnings() -> None:
    text = "\n".join(render(REPORT, color=False, now=0))
    assert "rover-1   TELEOP by station-1" in text
    assert "WARNINGS    LOW BATTERY (22.6 V)    STREAM NAVCAM FAILED" in text
    assert "battery    22.6 V  low" in text
    assert "heatsink 35/38 °C  motors 1.0/1.5 A" in text
    assert "37.983810, 23.727539  9 sats  hdop 0.9" in text
    assert "loss 2.0%" in text
    assert "rejected 1 (forged 1)" in text
    assert "accepted 120  dropped 2 (stale 2)" in text
    assert "streams    navcam failed" in text
    assert "lights     main ON  positional off  (positional: cannot request GPIO line" in text
    assert "turret     trigger ARMED  az 20.0°  el 5.0°  sight payload_camera playing" in text
    # A stale reading says so; a failed section shows its error, the others go on.
    assert "attitude   roll 1.5°  pitch -0.2°  yaw 271.0°  STALE (2.6 s old)" in text
    assert "computer   ERROR OSError: [Errno 5] Input/output error" in text
    assert "STALE" not in text.split("gps")[1].split("\n")[0]
    colored = "\n".join(render(REPORT, color=True, now=0))
    assert "\x1b[1;37;41m LOW BATTERY (22.6 V) \x1b[0m" in colored


def test_render_every_field_the_schema_has() -> None:
    """Every field of the sections the view shows is read from the schema's dataclasses: a
    report built from the schema renders without a blank where a value was sent."""
    text = "\n".join(render(REPORT, color=False, now=0))
    assert " ? " not in text
    assert "None" not in text


def test_another_schema_version_is_named_not_shown_as_blanks() -> None:
    text = "\n".join(render({**REPORT, "schema": SCHEMA_VERSION + 1}, color=False, now=0))
    assert f"telemetry schema v{SCHEMA_VERSION + 1}" in text
    assert f"reads v{SCHEMA_VERSION}" in text
    assert "battery" not in text


def test_frame_redraws_in_place_and_clips_to_the_terminal() -> None:
    drawn = frame(["\x1b[32m" + "x" * 50 + "\x1b[0m", "short"], width=10)
    assert drawn.startswith(HOME)
    assert drawn.endswith("\x1b[J")
    assert "\x1b[32m" + "x" * 10 + "\x1b[0m\x1b[K\n" in drawn


async def test_status_prints_connection_and_telemetry(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes
) -> None:
    platform = await platform_factory(quiet_platform_config("platform.id=rover-4"), fleet_key)
    platform.bus.publish(topics.LIGHTS_STATE, LightsState(main=False, positional=True))
    url = platform.ctx.signaling_url
    code, _, _ = await run_cli(station, "connect", "rover-4", "--url", url)
    assert code == 0
    code, out, err = await run_cli(station, "status", "rover-4")
    assert code == 0, err
    assert "session" in out
    assert "mode       autonomous" in out
    assert "lights     main off  positional ON" in out
    assert "WARNINGS   none" in out
    code, out, _ = await run_cli(station, "status", "rover-4", "--json")
    status = json.loads(out)
    assert status["telemetry"]["snapshot"]["lights"] == {
        "main": False,
        "positional": True,
        "errors": {},
    }
    assert status["telemetry"]["schema"] == SCHEMA_VERSION
    assert status["telemetry"]["link"]["received"] >= 1


async def test_status_watch_redraws_in_place(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes
) -> None:
    platform = await platform_factory(quiet_platform_config("platform.id=rover-5"), fleet_key)
    code, _, _ = await run_cli(station, "connect", "rover-5", "--url", platform.ctx.signaling_url)
    assert code == 0
    code, out, err = await run_cli(
        station, "status", "rover-5", "--watch", "--interval", "0.05", "--frames", "3"
    )
    assert code == 0, err
    assert out.count(HOME) == 3
    assert out.count("rover-5   AUTONOMOUS") == 3
    assert out.endswith("\x1b[?25h")  # the cursor is given back


async def test_status_watch_without_a_daemon_is_a_clear_error(station: StationDaemon) -> None:
    from conftest import free_tcp_port

    def absent() -> tuple[int, str]:
        err = io.StringIO()
        with contextlib.redirect_stderr(err):
            code = cli.main(
                ["status", "x", "--watch", "--set", f"station.api_port={free_tcp_port()}"]
            )
        return code, err.getvalue()

    code, err = await asyncio.to_thread(absent)
    assert code == 1
    assert "not running" in err


async def test_status_says_stale_when_the_gps_falls_silent(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes
) -> None:
    """A receiver on a pty sends a few epochs, then nothing: ``status`` says the fix is stale
    (after 3 periods of a 1 Hz receiver; the fix timeout is far off so it is not "NO FIX")."""
    master, slave = os.openpty()
    tty.setraw(slave)
    try:
        config = quiet_platform_config(
            "platform.id=rover-6",
            "gps.enabled=true",
            f"gps.port={os.ttyname(slave)}",
            "gps.fix_timeout=60",
        )
        platform = await platform_factory(config, fleet_key)
        # The port opens in a thread of its own: what is written before it is open is stale,
        # and dropped.
        await wait_until(lambda: getattr(platform.bus.last(topics.GPS_STATS), "connected", False))
        generator = NmeaGenerator(random.Random(6))
        pose = Pose(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 37.9415, 23.653, 42.0)
        start = datetime.datetime(2026, 11, 23, 12, 0, 0, tzinfo=datetime.UTC)
        for second in range(3):
            os.write(master, generator.epoch(pose, start + datetime.timedelta(seconds=second)))
        await wait_until(lambda: platform.bus.last(topics.GPS_FIX) is not None)
        url = platform.ctx.signaling_url
        code, _, _ = await run_cli(station, "connect", "rover-6", "--url", url)
        assert code == 0
        code, out, err = await run_cli(station, "status", "rover-6")
        assert code == 0, err
        (gps,) = [line for line in out.splitlines() if line.startswith("gps ")]
        assert "37.94" in gps
        assert "STALE" not in gps  # fresh: the last epoch just arrived

        async def gps_line() -> str:
            code, out, err = await run_cli(station, "status", "rover-6")
            assert code == 0, err
            (line,) = [line for line in out.splitlines() if line.startswith("gps ")]
            return line

        deadline = asyncio.get_running_loop().time() + 20
        while "STALE" not in (line := await gps_line()):
            assert asyncio.get_running_loop().time() < deadline, line
            await asyncio.sleep(0.5)
        assert "37.94" in line
        assert "s old)" in line  # the last fix, with its age
        code, out, _ = await run_cli(station, "status", "rover-6", "--json")
        gps_section = json.loads(out)["telemetry"]["snapshot"]["gps"]
        assert gps_section["stale"] is True
        assert gps_section["age_ms"] >= 3000
    finally:
        os.close(master)
        os.close(slave)
