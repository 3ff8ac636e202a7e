"""Memory after refused hostile imports: a refused file or map request costs a bounded scan of
its text, never a copy of it in lists, never the parsers or Shapely, and nothing stays after.
Before, a 150,001-vertex boundary held ~20 MB of parsed lists on the platform and each
refused file ~10 MB of matches on the station (RSS high-water kept by the allocator)."""

from __future__ import annotations

import json
import subprocess
import sys
import tracemalloc
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from support.cli import run_cli
from support.connected import connected
from support.hostile_files import boundary_map, kml, plan, ring
from support.patrol import LAT, LON, Robot
from support.velocity import open_connection

from brasidas.codecs import jsonrpc
from brasidas.codecs.jsonrpc import INVALID_PARAMS, Dispatcher, RpcError, request_text
from brasidas.mapfiles.errors import FileRefused
from stationd import mapfiles
from stationd.daemon import StationDaemon

SCAN_BOUND = 512 * 1024
"""What a refusal may allocate at its peak (the texts are 2-4 MB; a list of their matches is
several times that)."""

BIG_FILES: dict[str, tuple[Callable[[], str], Callable[[str], Any]]] = {
    "150,001-vertex boundary": (
        lambda: json.dumps(boundary_map(ring(150_001))),
        lambda text: mapfiles._read_map(text, "big.geojson", ("", "", False, False), None, 1 << 22),
    ),
    "172,000-coordinate KML": (
        lambda: kml(172_000),
        lambda text: mapfiles._read_map(text, "big.kml", ("", "", False, False), None, 1 << 22),
    ),
    "25,000-item plan": (
        lambda: plan(25_000),
        lambda text: mapfiles._read_route(text, "big.plan", (False, False), None, None, 1 << 22),
    ),
}


@pytest.mark.parametrize("name", list(BIG_FILES))
def test_a_refused_file_costs_a_bounded_scan_and_leaves_nothing(name: str) -> None:
    make, read = BIG_FILES[name]
    text = make()
    tracemalloc.start()
    try:
        before = tracemalloc.get_traced_memory()[0]
        for _ in range(5):  # repeated refusals: nothing accumulates
            tracemalloc.reset_peak()
            with pytest.raises(FileRefused, match="more than"):
                read(text)
            current, peak = tracemalloc.get_traced_memory()
            assert peak - before < SCAN_BOUND, f"{name}: {peak - before} bytes at the peak"
        assert current - before < 64 * 1024, f"{name}: {current - before} bytes kept"
    finally:
        tracemalloc.stop()


def test_a_refused_file_loads_neither_the_parsers_nor_shapely() -> None:
    """In a fresh interpreter (as a station that has read no file yet)."""
    script = (
        "import sys\n"
        "from stationd import mapfiles\n"
        "from brasidas.mapfiles.errors import FileRefused\n"
        f"text = {json.dumps(json.dumps(boundary_map(ring(150_001))))}\n"
        "try:\n"
        "    mapfiles._read_map(text, 'big.geojson', ('', '', False, False), None, 1 << 22)\n"
        "except FileRefused:\n"
        "    pass\n"
        "print(sorted(m for m in ('shapely', 'brasidas.mapfiles.files') if m in sys.modules))\n"
    )
    done = subprocess.run(
        [sys.executable, "-"],
        input=script,
        capture_output=True,
        text=True,
        timeout=60,
        check=True,
    )
    assert done.stdout.strip() == "[]", done.stderr


async def test_a_large_map_request_is_refused_before_it_is_parsed(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    dispatcher = Dispatcher()

    async def load_map(call: Any, map: Any) -> None:
        raise AssertionError("the map reached its handler")

    dispatcher.add("load_map", load_map, session_required=False)
    dispatcher.check_unparsed("load_map", lambda text: "refused" if len(text) > 1000 else None)

    def parsed(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("the request was parsed")

    monkeypatch.setattr(jsonrpc, "decode", parsed)
    monkeypatch.setattr(jsonrpc._INTERRUPTIBLE_DECODER, "decode", parsed)
    text = request_text("load_map", {"map": boundary_map(ring(30_000))}, 41)
    incoming = await dispatcher.parse_off_loop(text)
    assert incoming.parse_error is not None
    answer = json.loads(incoming.parse_error)
    assert answer["id"] == 41
    assert answer["error"]["code"] == INVALID_PARAMS
    assert answer["error"]["message"] == "refused"
    assert dispatcher.counters["refused_unparsed"] == 1


async def test_a_platform_refuses_a_150001_vertex_map_unparsed(robot_factory: Any) -> None:
    """Over a station's connection, as the issue's attacker with a session sent it."""
    robot: Robot = await robot_factory()
    before = await robot.call("get_map")
    conn = await open_connection(robot.daemon, None)
    try:
        with pytest.raises(RpcError, match="about 150002 vertices, more than 20000"):
            await conn.call("load_map", map=boundary_map(ring(150_001, LAT, LON)))
    finally:
        await conn.close()
    assert robot.ctx.rpc.counters["refused_unparsed"] == 1
    assert robot.ctx.rpc.counters["parse_errors"] == 0
    assert await robot.call("get_map") == before


async def test_the_operators_command_is_refused_before_the_station_parses_its_request(
    station: StationDaemon,
    platform_factory: Any,
    fleet_key: bytes,
    tmp_path: Path,
) -> None:
    """``brasidas-station map``/``route`` with each hostile file: the station's local API
    counts it in the request's text and answers with the file's name, parsing nothing."""
    await connected(station, platform_factory, fleet_key, tmp_path)
    files = {
        "big.geojson": ("map", json.dumps(boundary_map(ring(150_001))), "about 150002 vertices"),
        "big.kml": ("map", kml(172_000), "about 172000 vertices"),
        "big.plan": ("route", plan(25_000), "25000 mission items, more than 2000"),
    }
    for refused, (name, (command, text, reason)) in enumerate(files.items(), 1):
        (tmp_path / name).write_text(text)
        code, _, err = await run_cli(station, command, "rover-7", str(tmp_path / name))
        assert code == 1, err
        assert f"{name}: " in err, err
        assert reason in err, err
        assert "(not read)" in err, err
        assert station.ctx.api.counters["refused_unparsed"] == refused
