"""The Foxglove WebSocket's door (issue 26, defect 7): the console's Origin and Host rule.

The Foxglove SDK's server (:mod:`stationd.foxglove_live`) has no hook to refuse a WebSocket
upgrade by its headers, so it listens on an ephemeral loopback port and this TCP front takes
``foxglove.host:port``: it reads the upgrade request's head (bounded in size and time), answers
403 to a foreign ``Host`` or ``Origin`` exactly as the console's WebSocket does
(:func:`brasidas.rpc.browser_refusal`), and otherwise passes the bytes both ways untouched
(the handshake is the SDK's), but for a client that offers only the subprotocol's older name
(:mod:`stationd.foxglove_subprotocol`: renamed both ways in the handshake's heads).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import secrets

from brasidas.config import StationConfig
from brasidas.rpc import browser_refusal
from stationd.foxglove_subprotocol import name_legacy, offer_sdk

_LOGGER = logging.getLogger(__name__)

HEAD_MAX_BYTES = 16 * 1024
"""An upgrade request's head is well under this; a longer one is refused unread."""
HEAD_TIMEOUT_S = 5.0
"""A client that has not sent its whole head by then is dropped (a slow-loris holds nothing)."""
CHUNK = 64 * 1024
UPSTREAM_HOST = (
    f"127.{secrets.randbelow(254) + 1}.{secrets.randbelow(256)}.{secrets.randbelow(254) + 1}"
)
"""Where the SDK's own server listens: a random loopback address (Linux answers all of 127/8)
as well as an ephemeral port, so a web page cannot find it by scanning 127.0.0.1's ports and
go round the guard."""


def head_refusal(head: bytes, local_hosts: frozenset[str], origins: tuple[str, ...]) -> str | None:
    """Why the upgrade request ``head`` (up to its blank line) is refused, or None."""
    lines = head.decode("latin-1").split("\r\n")
    headers: dict[str, str] = {}
    for line in lines[1:]:
        name, sep, value = line.partition(":")
        if sep:
            key = name.strip().lower()
            if key in headers and key in ("host", "origin"):
                return f"more than one {name.strip()} header"
            headers[key] = value.strip()
    host = headers.get("host")
    if host is None:
        return "no Host header"
    return browser_refusal(host, headers.get("origin"), local_hosts, origins)


class OriginGuard:
    """Listens on ``host:port``; each admitted client is spliced to the upstream server."""

    def __init__(
        self,
        host: str,
        port: int,
        upstream_host: str,
        upstream_port: int,
        local_hosts: frozenset[str],
        origins: tuple[str, ...] = (),
    ) -> None:
        self.host = host
        self.port = port
        self.upstream_host = upstream_host
        self.upstream_port = upstream_port
        self.local_hosts = local_hosts
        self.origins = origins
        self.refused = 0
        self._server: asyncio.Server | None = None
        self._writers: set[asyncio.StreamWriter] = set()

    async def start(self) -> int:
        """Bind; the bound port (the kernel's choice for 0)."""
        self._server = await asyncio.start_server(
            self._client, self.host, self.port, limit=HEAD_MAX_BYTES
        )
        self.port = int(self._server.sockets[0].getsockname()[1])
        return self.port

    async def close(self) -> None:
        """Stop listening and cut every spliced connection. Idempotent."""
        server, self._server = self._server, None
        if server is not None:
            server.close()
        for writer in list(self._writers):
            writer.close()
        if server is not None:
            await server.wait_closed()

    async def _client(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self._writers.add(writer)
        try:
            await self._serve(reader, writer)
        except (ConnectionError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
            pass
        except TimeoutError:
            pass
        finally:
            self._writers.discard(writer)
            writer.close()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HEAD_TIMEOUT_S)
        refusal = head_refusal(head, self.local_hosts, self.origins)
        if refusal is not None:
            self.refused += 1
            _LOGGER.warning("foxglove: refused %s: %s", writer.get_extra_info("peername"), refusal)
            body = refusal.encode()
            writer.write(
                b"HTTP/1.1 403 Forbidden\r\nContent-Type: text/plain; charset=utf-8\r\n"
                b"Content-Length: %d\r\nConnection: close\r\n\r\n%s" % (len(body), body)
            )
            with contextlib.suppress(ConnectionError):
                await writer.drain()
            return
        head, legacy = offer_sdk(head)
        up_reader, up_writer = await asyncio.open_connection(self.upstream_host, self.upstream_port)
        self._writers.add(up_writer)
        try:
            up_writer.write(head)
            if legacy:  # the SDK's answer names foxglove.sdk.v1: the client offered the old name
                answer = await asyncio.wait_for(up_reader.readuntil(b"\r\n\r\n"), HEAD_TIMEOUT_S)
                writer.write(name_legacy(answer))
            async with asyncio.TaskGroup() as group:
                group.create_task(_pipe(reader, up_writer))
                group.create_task(_pipe(up_reader, writer))
        finally:
            self._writers.discard(up_writer)
            up_writer.close()


async def _pipe(source: asyncio.StreamReader, sink: asyncio.StreamWriter) -> None:
    """Copy until end of stream, then half-close (the other direction may still run)."""
    try:
        while data := await source.read(CHUNK):
            sink.write(data)
            await sink.drain()
    except ConnectionError:
        pass
    finally:
        if sink.can_write_eof():
            with contextlib.suppress(OSError):
                sink.write_eof()
        else:
            sink.close()


def guard_for(
    config: StationConfig, upstream_host: str, upstream_port: int, port: int
) -> OriginGuard:
    """The guard on ``foxglove.host:port`` with the console's host names."""
    foxglove = config.foxglove
    local_hosts = frozenset(
        {"127.0.0.1", "localhost", "[::1]", foxglove.host, *config.console.https_names}
    )
    return OriginGuard(
        foxglove.host, port, upstream_host, upstream_port, local_hosts, foxglove.origins
    )
