"""The station's local API for a platform's recordings (issue 23): list them, and where to
download one (the platform's signaling URL and this station's session token: the CLI then
fetches the file itself, over HTTP with ranges, so a cut download resumes)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import re
from pathlib import Path
from typing import Any
from urllib.parse import quote

import aiohttp

from brasidas.codecs.jsonrpc import INVALID_PARAMS, CallContext, RpcError
from brasidas.recording import NAME_PATTERN, SESSION_HEADER
from brasidas.recording.writer import ACTIVE_SUFFIX
from brasidas.security import state_dir
from stationd.context import StationContext
from stationd.replay import recording_index, recording_state

_LOGGER = logging.getLogger(__name__)


class DownloadError(Exception):
    """A download that failed or was refused (the message says which)."""


async def download(url: str, headers: dict[str, str], target: Path, have: int) -> int:
    """GET ``url`` into ``target``, resuming after the ``have`` bytes it already holds (an
    HTTP range); the file's final size. The recording being written is fetched whole each
    time: the platform hands out a new complete copy per request, which a range would splice."""
    if have and not url.endswith(ACTIVE_SUFFIX):
        headers = {**headers, "Range": f"bytes={have}-"}
    timeout = aiohttp.ClientTimeout(total=None, sock_connect=10, sock_read=30)
    try:
        async with (
            aiohttp.ClientSession(timeout=timeout) as session,
            session.get(url, headers=headers) as response,
        ):
            if response.status == 416 and have:
                return have  # nothing past what we have: already complete
            if response.status not in (200, 206):
                text = (await response.text())[:200]
                raise DownloadError(f"download refused ({response.status}): {text}")
            size = have if response.status == 206 else 0
            mode = "ab" if response.status == 206 else "wb"
            with open(target, mode) as out:  # noqa: ASYNC230 (each write goes to a thread)
                async for chunk in response.content.iter_chunked(256 * 1024):
                    await asyncio.to_thread(out.write, chunk)
                    size += len(chunk)
    except aiohttp.ClientError as err:
        raise DownloadError(f"download failed: {err} (run it again to resume)") from None
    return size


def trim_cache(cache: Path, max_bytes: int, keep: frozenset[Path]) -> list[Path]:
    """Delete cached recordings (and partial downloads), least recently opened first, until
    the cache holds at most ``max_bytes``; never those in ``keep`` (being opened or fetched).
    Blocking: call it in a thread."""
    found: list[tuple[float, Path, int]] = []
    for path in cache.glob("*/*"):
        if path.name.endswith((".mcap", ".mcap.part")):
            with contextlib.suppress(OSError):  # gone meanwhile
                info = path.stat()
                found.append((info.st_mtime, path, info.st_size))
    total = sum(size for _mtime, _path, size in found)
    deleted: list[Path] = []
    for _mtime, path, size in sorted(found):
        if total <= max_bytes:
            break
        if path in keep:
            continue
        path.unlink(missing_ok=True)
        total -= size
        deleted.append(path)
        _LOGGER.info("replay cache: deleted %s (replay.max_bytes)", path.name)
    return deleted


class RecordingsApi:
    def __init__(self, ctx: StationContext) -> None:
        self.ctx = ctx
        self.cache = state_dir() / "replay"
        """Recordings fetched for replay, by platform, within ``replay.max_bytes``."""
        self._fetching: dict[Path, asyncio.Lock] = {}

    async def api_recordings_list(self, call: CallContext, platform_id: str) -> Any:
        """The platform's recordings and its recorder's state."""
        connection = await self.ctx.connection(platform_id)
        return await connection.call("list_recordings")

    async def api_recording_source(
        self, call: CallContext, platform_id: str, name: str
    ) -> dict[str, Any]:
        """Where to download recording ``name``: its URL and the header to send."""
        connection = await self.ctx.connection(platform_id)
        return {
            "url": f"{connection.signaling_url}/recordings/{quote(name, safe='')}",
            "headers": {SESSION_HEADER: connection.session_id},
        }

    async def _local(self, platform_id: str, name: str) -> Path:
        """The recording, fetched from the platform into the cache once (finished ones only)."""
        if not NAME_PATTERN.match(name) or not re.match(r"^[A-Za-z0-9._-]{1,64}$", platform_id):
            raise RpcError(INVALID_PARAMS, f"invalid params: not a finished recording: {name!r}")
        path = self.cache / platform_id / name
        lock = self._fetching.setdefault(path, asyncio.Lock())
        async with lock:
            if await asyncio.to_thread(path.is_file):
                with contextlib.suppress(OSError):  # its use, for the cache's order
                    await asyncio.to_thread(os.utime, path)
                return path
            partial = path.with_name(name + ".part")
            await asyncio.to_thread(partial.parent.mkdir, parents=True, exist_ok=True)
            have = await asyncio.to_thread(
                lambda: partial.stat().st_size if partial.exists() else 0
            )
            source = await self.api_recording_source(CallContext(), platform_id, name)
            try:
                await download(source["url"], source["headers"], partial, have)
            except DownloadError as err:
                raise RpcError(INVALID_PARAMS, str(err)) from None
            await asyncio.to_thread(partial.rename, path)
            busy = frozenset(
                p.with_name(p.name + ".part") if p != path else p
                for p, other in self._fetching.items()
                if p == path or other.locked()
            )
            await asyncio.to_thread(trim_cache, self.cache, self.ctx.config.replay.max_bytes, busy)
            return path

    async def api_recording_open(
        self, call: CallContext, platform_id: str, name: str
    ) -> dict[str, Any]:
        """Fetch a recording for replay: its span, channels and track."""
        path = await self._local(platform_id, name)
        try:
            return {"name": name, **await asyncio.to_thread(recording_index, path)}
        except Exception as err:
            raise RpcError(INVALID_PARAMS, f"cannot read {name}: {err}") from None

    async def api_recording_state(
        self,
        call: CallContext,
        platform_id: str,
        name: str,
        time_ns: int,
        frames_after_ns: int | None = None,
    ) -> dict[str, Any]:
        """The state at ``time_ns``: position, telemetry, log and the frames to decode (while
        playing: those after ``frames_after_ns``, which the console's decoder has had)."""
        if not isinstance(time_ns, int) or isinstance(time_ns, bool):
            raise RpcError(INVALID_PARAMS, "invalid params: time_ns must be an integer")
        if frames_after_ns is not None and (
            not isinstance(frames_after_ns, int) or isinstance(frames_after_ns, bool)
        ):
            raise RpcError(INVALID_PARAMS, "invalid params: frames_after_ns must be an integer")
        path = await self._local(platform_id, name)
        try:
            return await asyncio.to_thread(recording_state, path, time_ns, frames_after_ns)
        except Exception as err:
            raise RpcError(INVALID_PARAMS, f"cannot read {name}: {err}") from None


async def async_setup(ctx: StationContext) -> None:
    api = RecordingsApi(ctx)
    for name in ("recordings_list", "recording_source", "recording_open", "recording_state"):
        ctx.api.add(name, getattr(api, f"api_{name}"), session_required=False)
