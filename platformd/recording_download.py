"""Recording downloads at a bounded rate: every download together gets
``recorder.download_kib_s``, each source address an equal part while others download, so 16
parallel downloaders cannot take the radio link (or the platform's CPU) from the operator's
video and control.

The rate is the platform's one account of bytes sent on a source's behalf
(:class:`brasidas.admission.SourceLedger`: each chunk reserves its slot there);
:func:`send_file` streams one file, ranges honoured, reading in a worker thread.
"""

from __future__ import annotations

import asyncio
import os
import re
from pathlib import Path
from typing import BinaryIO

from aiohttp import web

from brasidas.admission import SourceLedger

CHUNK = 64 * 1024
EMPTY_SUFFIX = re.compile(r"bytes\s*=\s*-0+\s*", re.IGNORECASE)
"""``Range: bytes=-0``, the last zero bytes: unsatisfiable (RFC 9110 14.1.1; aiohttp reads it
as the whole file)."""


async def send_file(
    request: web.Request, path: Path, ledger: SourceLedger, host: str, headers: dict[str, str]
) -> web.StreamResponse:
    """``path`` (a regular file, checked by the caller) with ``Range`` honoured, at ``host``'s
    share of the download rate (charged to it). A file still being written is sent up to its
    size when the request came."""
    handle = await asyncio.to_thread(_open, path)
    try:
        size = os.fstat(handle.fileno()).st_size
        start, end = _range(request, size)
        response = web.StreamResponse(
            status=206 if request.headers.get("Range") else 200,
            headers={**headers, "Accept-Ranges": "bytes", "Content-Length": str(end - start)},
        )
        if request.headers.get("Range"):
            response.headers["Content-Range"] = f"bytes {start}-{end - 1}/{size}"
        await response.prepare(request)
        await asyncio.to_thread(handle.seek, start)
        loop = asyncio.get_running_loop()
        left = end - start
        while left > 0:
            data = await asyncio.to_thread(handle.read, min(CHUNK, left))
            if not data:
                break
            delay = ledger.reserve_download(host, len(data), loop.time())
            if delay > 0:
                await asyncio.sleep(delay)
            await response.write(data)
            left -= len(data)
        await response.write_eof()
        return response
    finally:
        await asyncio.to_thread(handle.close)


def _open(path: Path) -> BinaryIO:
    return path.open("rb")


def _range(request: web.Request, size: int) -> tuple[int, int]:
    """(start, end) of what to send; 416 for a range that cannot be satisfied."""
    header = request.headers.get("Range", "")
    if not header:
        return 0, size
    if EMPTY_SUFFIX.fullmatch(header.strip()):
        raise _unsatisfiable(size)
    try:
        wanted = request.http_range
    except ValueError:
        raise _unsatisfiable(size) from None
    start, stop = wanted.start, wanted.stop
    if start is None:
        start = 0
    if start < 0:  # bytes=-N: the last N
        start = max(0, size + start)
        stop = size
    stop = size if stop is None else min(stop, size)
    if start >= stop:
        raise _unsatisfiable(size)
    return start, stop


def _unsatisfiable(size: int) -> web.HTTPRequestRangeNotSatisfiable:
    return web.HTTPRequestRangeNotSatisfiable(headers={"Content-Range": f"bytes */{size}"})
