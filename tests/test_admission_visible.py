"""Issue 19's admission made visible: a real platform flooded with idle connections from
loopback shows it in telemetry's admission section, in ``brasidas-station status`` and as
the station's warning 90.24 (connections refused from the flooding address)."""

from __future__ import annotations

import asyncio
import json
import socket
import time
from collections.abc import AsyncIterator, Awaitable, Callable

import pytest
from conftest import quiet_platform_config, running_station
from support.cli import run_cli

from brasidas.codecs.telemetry_schema import Admission
from platformd.app import PlatformDaemon
from stationd.daemon import StationDaemon

Factory = Callable[..., Awaitable[PlatformDaemon]]

ATTACKER = "127.0.0.2"
"""The flood's own loopback address: the station connects from 127.0.0.1."""


@pytest.fixture
async def station(fleet_key: bytes) -> AsyncIterator[StationDaemon]:
    async with running_station(
        fleet_key, "telemetry.refused_warn=50", "station.connect_timeout=2"
    ) as daemon:
        yield daemon


def idle_connection(address: tuple[str, int]) -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind((ATTACKER, 0))
    sock.connect(address)
    return sock


async def test_a_flood_of_idle_connections_shows_in_telemetry_status_and_a_warning(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes
) -> None:
    platform = await platform_factory(quiet_platform_config("platform.id=rover-7"), fleet_key)
    url = platform.ctx.signaling_url
    host, port = url.removeprefix("http://").rsplit(":", 1)
    code, _, err = await run_cli(station, "connect", "rover-7", "--url", url)
    assert code == 0, err
    code, out, err = await run_cli(station, "status", "rover-7")
    assert code == 0, err
    assert "admission" not in out
    assert "WARNINGS   none" in out  # nothing refused yet

    idle = [idle_connection((host, int(port))) for _ in range(120)]
    try:
        # The platform's own view: 8 held (the per-host cap), the rest refused, by address.
        section = platform.ctx.telemetry.build_one(Admission)
        deadline = time.monotonic() + 20
        while not (isinstance(section, Admission) and section.refused >= 112):
            assert time.monotonic() < deadline, section
            await asyncio.sleep(0.05)
            section = platform.ctx.telemetry.build_one(Admission)
        assert section.refusing == ATTACKER
        assert section.window_s == 10.0
        at_cap = section.counters.get("refused_host", 0) + section.counters.get("evicted_host", 0)
        assert at_cap == section.refused
        assert section.strangers == 8

        # The station's: the status line and the warning, through telemetry datagrams.
        deadline = time.monotonic() + 20
        while True:
            code, out, err = await run_cli(station, "status", "rover-7")
            assert code == 0, err
            if "CONNECTIONS REFUSED" in out or time.monotonic() > deadline:
                break
            await asyncio.sleep(0.2)
        assert f"CONNECTIONS REFUSED FROM {ATTACKER}: {section.refused} IN 10 S" in out, out
        line = next(line for line in out.splitlines() if line.startswith("admission"))
        assert f"refused {section.refused} from {ATTACKER} in 10 s" in line
        assert "since start: " in line
        assert "_host " in line
        assert "strangers now 8" in line
        code, out, _ = await run_cli(station, "status", "rover-7", "--json")
        warnings = json.loads(out)["telemetry"]["warnings"]
        assert [w["code"] for w in warnings if w["name"] == "connections_refused"] == ["90.24"]
    finally:
        for sock in idle:
            sock.close()
