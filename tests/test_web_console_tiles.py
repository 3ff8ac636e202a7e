"""The map's offline background (issue 31): the operator's own tiles from an MBTiles file,
served by the station and drawn under the map in headless Chromium; a tile URL's tiles
fetched once from a (loopback) tile server and served from the station's copies after."""

from __future__ import annotations

import asyncio
import math
import sqlite3
import struct
import zlib
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import aiohttp
import pytest_asyncio
from aiohttp import web
from conftest import running_station
from support.console import Factory, console, rover, screenshots

from stationd.daemon import StationDaemon

LAT, LON = 37.9415, 23.6530  # where the --sim rover starts (support.console.rover)


def png(rgb: tuple[int, int, int], size: int = 256) -> bytes:
    """A solid-colour PNG (a real image the browser decodes)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))

    rows = b"".join(b"\x00" + bytes(rgb) * size for _ in range(size))
    header = struct.pack(">IIBBBBB", size, size, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", header) + chunk(b"IDAT", zlib.compress(rows))


def tile_of(lat: float, lon: float, z: int) -> tuple[int, int]:
    rad = math.radians(lat)
    x = int((lon + 180) / 360 * 2**z)
    y = int((1 - math.log(math.tan(rad) + 1 / math.cos(rad)) / math.pi) / 2 * 2**z)
    return x, y


def write_mbtiles(path: Path) -> dict[tuple[int, int, int], bytes]:
    """Tiles 3 by 3 around the rover at zooms 14-20; TMS rows, as MBTiles keeps them."""
    tiles: dict[tuple[int, int, int], bytes] = {}
    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE metadata (name TEXT, value TEXT)")
        db.execute(
            "CREATE TABLE tiles (zoom_level INTEGER, tile_column INTEGER, tile_row INTEGER,"
            " tile_data BLOB)"
        )
        db.execute("INSERT INTO metadata VALUES ('format', 'png')")
        for z in range(14, 21):
            cx, cy = tile_of(LAT, LON, z)
            for x in range(cx - 1, cx + 2):
                for y in range(cy - 1, cy + 2):
                    data = png((40 + z * 5, 90, 60 + (x + y) % 2 * 40))
                    tiles[(z, x, y)] = data
                    db.execute(
                        "INSERT INTO tiles VALUES (?, ?, ?, ?)", (z, x, (1 << z) - 1 - y, data)
                    )
    return tiles


@pytest_asyncio.fixture(loop_scope="session")  # its one test is a browser test
async def tiled(
    fleet_key: bytes, tmp_path: Path
) -> AsyncIterator[tuple[StationDaemon, dict[tuple[int, int, int], bytes]]]:
    tiles = write_mbtiles(tmp_path / "area.mbtiles")
    async with running_station(fleet_key, f"console.tiles={tmp_path / 'area.mbtiles'}") as daemon:
        yield daemon, tiles


async def test_mbtiles_are_served_and_drawn_under_the_map(
    tiled: tuple[StationDaemon, dict[tuple[int, int, int], bytes]],
    platform_factory: Factory,
    fleet_key: bytes,
    browser: Any,
) -> None:
    from playwright.async_api import expect

    station, tiles = tiled
    base = f"http://127.0.0.1:{station.api_port}"
    (z, x, y), data = next(iter(tiles.items()))
    async with aiohttp.ClientSession() as http:
        async with http.get(f"{base}/tiles/{z}/{x}/{y}") as response:  # XYZ row, not TMS
            assert response.status == 200
            assert response.content_type == "image/png"
            assert await response.read() == data
        async with http.get(f"{base}/tiles/{z}/{x + 5}/{y}") as response:
            assert response.status == 404
        async with http.get(f"{base}/tiles/3/99/0") as response:
            assert response.status == 400
    await rover(platform_factory, fleet_key, station)
    page = await console(browser, station, "web-rover")
    drawn = page.locator("#map img.basemap-tile")
    await expect(drawn.first).to_be_attached(timeout=15_000)
    loop = asyncio.get_running_loop()
    deadline = loop.time() + 10
    while True:  # the browser decoded the station's tiles (a missing one is not counted)
        loaded = await drawn.evaluate_all("images => images.filter(i => i.naturalWidth).length")
        if loaded >= 1:
            break
        assert loop.time() < deadline, "no tile image loaded"
        await asyncio.sleep(0.2)
    await screenshots(page, "console-tiles")
    await page.get_by_text("map files and background").click()  # folded
    await page.get_by_label("tiles", exact=True).uncheck()
    await expect(drawn).to_have_count(0)


async def test_a_tile_urls_tiles_are_kept_and_served_offline(
    fleet_key: bytes, tmp_path: Path
) -> None:
    served: list[str] = []
    tile = png((10, 200, 10))

    async def handler(request: web.Request) -> web.Response:
        served.append(request.path)
        if request.match_info["z"] == "9":
            raise web.HTTPNotFound()
        return web.Response(body=tile, content_type="image/png")

    app = web.Application()
    app.router.add_get("/{z}/{x}/{y}.png", handler)
    runner = web.AppRunner(app)
    await runner.setup()
    site = web.TCPSite(runner, "127.0.0.1", 0)
    await site.start()
    port = site._server.sockets[0].getsockname()[1]  # type: ignore[union-attr]
    settings = (
        f"console.tiles=http://127.0.0.1:{port}/{{z}}/{{x}}/{{y}}.png",
        f"console.tiles_cache={tmp_path / 'cache'}",
    )
    try:
        async with (
            running_station(fleet_key, *settings) as station,
            aiohttp.ClientSession() as http,
        ):
            url = f"http://127.0.0.1:{station.api_port}/tiles/16/100/200"
            for _ in range(2):
                async with http.get(url) as response:
                    assert response.status == 200
                    assert await response.read() == tile
            assert served == ["/16/100/200.png"]  # the second from the station's copy
            assert (tmp_path / "cache" / "16" / "100" / "200").read_bytes() == tile
            async with http.get(f"http://127.0.0.1:{station.api_port}/tiles/9/1/1") as response:
                assert response.status == 404
        await runner.cleanup()  # the tile server gone: the kept tile is still served
        async with (
            running_station(fleet_key, *settings) as station,
            aiohttp.ClientSession() as http,
        ):
            url = f"http://127.0.0.1:{station.api_port}/tiles/16/100/200"
            async with http.get(url) as response:
                assert response.status == 200
                assert await response.read() == tile
            async with http.get(url.replace("/200", "/201")) as response:
                assert response.status == 502
    finally:
        await runner.cleanup()
