"""The map's offline background (issue 31): the operator's own tiles, served to the console at
``/tiles/{z}/{x}/{y}`` from an MBTiles file or from a tile URL's copies kept on disk.

``console.tiles`` names the source: a path ending ``.mbtiles`` (SQLite, TMS rows: y counted
from the south) or a URL template with ``{z}``, ``{x}``, ``{y}``. A URL's tile is fetched
once, kept under ``console.tiles_cache`` and served from there afterwards (offline). A
missing tile is 404; an unreachable server 502. Files and SQLite are read in threads.
"""

from __future__ import annotations

import asyncio
import logging
import os
import sqlite3
import tempfile
from pathlib import Path

import aiohttp
from aiohttp import web

from brasidas.config import ConsoleSection
from brasidas.security import state_dir

_LOGGER = logging.getLogger(__name__)

MAX_ZOOM = 22
MAX_TILE_BYTES = 1 << 20
"""A tile larger than this from a tile server is refused (a tile is tens of kB)."""
FETCHES_AT_ONCE = 4
FETCH_TIMEOUT_S = 10.0
TYPES = {b"\x89PNG": "image/png", b"\xff\xd8\xff": "image/jpeg", b"RIFF": "image/webp"}


def content_type(data: bytes) -> str | None:
    """The image type of a tile's bytes (PNG, JPEG, WebP), None for anything else."""
    return next((kind for magic, kind in TYPES.items() if data.startswith(magic)), None)


class TileSource:
    """One configured source of tiles; ``tile(z, x, y)``: the bytes or None (none there)."""

    def __init__(self, console: ConsoleSection) -> None:
        self.spec = console.tiles
        self.mbtiles = Path(self.spec) if self.spec.lower().endswith(".mbtiles") else None
        self.cache = Path(console.tiles_cache) if console.tiles_cache else state_dir() / "tiles"
        self._fetching = asyncio.Semaphore(FETCHES_AT_ONCE)
        self._session: aiohttp.ClientSession | None = None

    async def tile(self, z: int, x: int, y: int) -> bytes | None:
        if self.mbtiles is not None:
            return await asyncio.to_thread(self._from_mbtiles, z, x, y)
        kept = self.cache / str(z) / str(x) / str(y)
        data = await asyncio.to_thread(_read, kept)
        if data is None:
            data = await self._fetch(z, x, y)
            if data is not None:
                await asyncio.to_thread(_keep, kept, data)
        return data

    def _from_mbtiles(self, z: int, x: int, y: int) -> bytes | None:
        """(Worker thread.) MBTiles rows count y from the south (TMS)."""
        assert self.mbtiles is not None
        uri = f"{self.mbtiles.resolve().as_uri()}?mode=ro"
        with sqlite3.connect(uri, uri=True) as db:
            row = db.execute(
                "SELECT tile_data FROM tiles WHERE zoom_level=? AND tile_column=? AND tile_row=?",
                (z, x, (1 << z) - 1 - y),
            ).fetchone()
        return bytes(row[0]) if row else None

    async def _fetch(self, z: int, x: int, y: int) -> bytes | None:
        url = self.spec.replace("{z}", str(z)).replace("{x}", str(x)).replace("{y}", str(y))
        async with self._fetching:
            if self._session is None:
                self._session = aiohttp.ClientSession(
                    timeout=aiohttp.ClientTimeout(total=FETCH_TIMEOUT_S)
                )
            async with self._session.get(url) as response:
                if response.status == 404:
                    return None
                response.raise_for_status()
                data = await response.content.read(MAX_TILE_BYTES + 1)
        if len(data) > MAX_TILE_BYTES or content_type(data) is None:
            raise ValueError(f"{url}: not a tile image of at most {MAX_TILE_BYTES} bytes")
        return data

    async def close(self) -> None:
        if self._session is not None:
            await self._session.close()


def _read(path: Path) -> bytes | None:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        return None


def _keep(path: Path, data: bytes) -> None:
    """(Worker thread.) Written whole or not at all: a half tile is never served."""
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, name = tempfile.mkstemp(dir=path.parent, prefix=".tile-")
    with os.fdopen(handle, "wb") as file:
        file.write(data)
    os.replace(name, path)


def add_tile_routes(app: web.Application, console: ConsoleSection) -> None:
    """``/tiles.json`` (whether there are tiles) and ``/tiles/{z}/{x}/{y}``."""
    source = TileSource(console) if console.tiles else None

    async def about(request: web.Request) -> web.Response:
        kind = None if source is None else "mbtiles" if source.mbtiles else "url"
        return web.json_response({"tiles": source is not None, "kind": kind})

    async def tile(request: web.Request) -> web.Response:
        if source is None:
            raise web.HTTPNotFound(text="no tiles configured (console.tiles)")
        try:
            z, x, y = (int(request.match_info[name]) for name in ("z", "x", "y"))
        except ValueError:
            raise web.HTTPBadRequest(text="z, x and y are whole numbers") from None
        if not (0 <= z <= MAX_ZOOM and 0 <= x < 1 << z and 0 <= y < 1 << z):
            raise web.HTTPBadRequest(text=f"no tile {z}/{x}/{y}")
        try:
            data = await source.tile(z, x, y)
        except (OSError, sqlite3.Error, aiohttp.ClientError, ValueError, TimeoutError) as err:
            _LOGGER.warning("tile %d/%d/%d: %s", z, x, y, err)
            raise web.HTTPBadGateway(text=f"tile {z}/{x}/{y}: {err}") from None
        if data is None:
            raise web.HTTPNotFound(text=f"no tile {z}/{x}/{y}")
        kind = content_type(data) or "application/octet-stream"
        return web.Response(body=data, content_type=kind, headers={"Cache-Control": "max-age=3600"})

    async def close(app: web.Application) -> None:
        if source is not None:
            await source.close()

    app.router.add_get("/tiles.json", about)
    app.router.add_get("/tiles/{z}/{x}/{y}", tile)
    app.on_cleanup.append(close)
