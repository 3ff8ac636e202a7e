"""``brasidas-station status ID [--watch]``: the rendering, and the CLI against live daemons."""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
from collections.abc import AsyncIterator, Awaitable, Callable

import pytest
from conftest import quiet_platform_config

from brasidas import topics
from brasidas.config import StationConfig, load_config
from brasidas.messages import LightsState
from platformd.app import PlatformDaemon
from stationd import cli
from stationd.daemon import StationDaemon
from stationd.status_view import HOME, frame, render

Factory = Callable[..., Awaitable[PlatformDaemon]]

REPORT = {
    "platform_id": "rover-1",
    "snapshot": {
        "mode": "teleop",
        "manual_override": True,
        "override": {"engaged": True, "station": "station-1"},
        "lights": {"main": True, "positional": False},
        "battery": {"volts": 22.6, "level": "low", "monitor": True},
        "controller": {"connected": True, "temps_c": [35.0, 38.0], "amps": [1.0, 1.5]},
        "gps": {"fix": True, "latitude": 37.9838096, "longitude": 23.7275388, "satellites": 9},
        "attitude": {"roll": 1.5, "pitch": -0.25, "yaw": 271.0},
        "computer": {"cpu_temp_c": None, "load": [0.1, 0.2, 0.3], "mem_free_mb": 812.0},
        "link": {"velocity": {"accepted": 120, "dropped": {"stale": 2, "forged": 0}}},
        "streams": {"navcam": "failed"},
        "autonomy": None,
        "diagnostics": None,
    },
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
    assert "37.983810, 23.727539  9 sats" in text
    assert "roll 1.5°  pitch -0.2°  yaw 271.0°" in text
    assert "cpu -  load 0.10 0.20 0.30  mem free 812 MB" in text
    assert "loss 2.0%" in text and "rejected 1 (forged 1)" in text
    assert "accepted 120  dropped 2 (stale 2)" in text
    assert "streams    navcam failed" in text
    colored = "\n".join(render(REPORT, color=True, now=0))
    assert "\x1b[1;37;41m LOW BATTERY (22.6 V) \x1b[0m" in colored


def test_frame_redraws_in_place_and_clips_to_the_terminal() -> None:
    drawn = frame(["\x1b[32m" + "x" * 50 + "\x1b[0m", "short"], width=10)
    assert drawn.startswith(HOME) and drawn.endswith("\x1b[J")
    assert "\x1b[32m" + "x" * 10 + "\x1b[0m\x1b[K\n" in drawn


@pytest.fixture
async def station(fleet_key: bytes) -> AsyncIterator[StationDaemon]:
    config = load_config(StationConfig, None, ["station.api_port=0", "station.connect_timeout=2"])
    daemon = StationDaemon(config, fleet_key)
    await daemon.start()
    yield daemon
    await daemon.stop()


async def run_cli(station: StationDaemon, *argv: str) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    api = ["--set", f"station.api_port={station.api_port}"]

    def call() -> int:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            return cli.main([*argv, *api])

    code = await asyncio.to_thread(call)
    return code, out.getvalue(), err.getvalue()


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
    assert "session" in out and "mode       autonomous" in out
    assert "lights     main off  positional ON" in out and "WARNINGS   none" in out
    code, out, _ = await run_cli(station, "status", "rover-4", "--json")
    status = json.loads(out)
    assert status["telemetry"]["snapshot"]["lights"] == {"main": False, "positional": True}
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
    assert out.count(HOME) == 3 and out.count("rover-5   AUTONOMOUS") == 3
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
    assert code == 1 and "not running" in err
