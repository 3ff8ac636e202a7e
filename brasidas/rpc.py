"""JSON-RPC transports over aiohttp: HTTP POST and WebSocket server routes, and a WebSocket client."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import logging
import socket
from collections.abc import Awaitable, Callable, Sequence
from typing import TYPE_CHECKING, Any

import aiohttp
from aiohttp import web

from brasidas.actor import Actor, Supervisor, wait_forever
from brasidas.admission import (
    AdmissionLimits,
    AdmissionPolicy,
    AdmittingListener,
    ServerAdmission,
    Slot,
)
from brasidas.bus import Bus
from brasidas.codecs.jsonrpc import (
    INTERNAL_ERROR,
    LARGE_MESSAGE_BYTES,
    REQUEST_TOO_LARGE,
    TIMEOUT,
    UNAUTHORIZED,
    BadAnswer,
    CallContext,
    Dispatcher,
    EncodedParams,
    Incoming,
    RpcError,
    decode,
    decode_answer_message,
    encode_error,
    read_answer,
    request_text,
)
from brasidas.limits import ANSWER_MAX_BYTES, MAP_REQUEST_MAX_BYTES

if TYPE_CHECKING:
    import ssl  # only the station's HTTPS console: the platform keeps ssl out (~4 MB)

_LOGGER = logging.getLogger(__name__)

MAX_IN_FLIGHT_PER_SOCKET = 32

READER_RESUME_DELAY = 0.005
"""After a fast-path call the reader task receives again this much later (s), unless the
caller's next call reads first: back-to-back calls cost no loop turn for handing over. Idle
messages (a push, the connection's end) wait in aiohttp's buffer meanwhile, never lost."""

TRUSTED = AdmissionLimits(trusted=True)
"""The default admission: caps and timeouts on every connection, none counted a stranger's."""

STRANGER_MAX_BYTES = 4096
"""Requests on a connection without a session are at most this long (``challenge`` and
``connect`` need well under 1 KiB): a stranger's flood is never parsed."""

_CONNECTION_ENDED = (aiohttp.WSMsgType.CLOSE, aiohttp.WSMsgType.CLOSING, aiohttp.WSMsgType.CLOSED)


def browser_refusal(
    host: str, origin: str | None, local_hosts: frozenset[str], origins: tuple[str, ...] = ()
) -> str | None:
    """Why a local server refuses a request a web page elsewhere could make through the
    operator's browser (answered 403), or None: a ``Host`` not among ``local_hosts`` (DNS
    rebinding), an ``Origin`` that is neither this very server nor one of ``origins``
    (cross-site requests, and WebSockets, which browsers do not hold to CORS)."""
    name = host.rsplit(":", 1)[0] if not host.endswith("]") else host
    if name not in local_hosts:
        return f"host {host!r} not served"
    if origin is not None and origin.split("://", 1)[-1] != host and origin not in origins:
        return "cross-origin request refused"
    return None


def add_rpc_routes(
    app: web.Application,
    dispatcher: Dispatcher,
    path: str,
    max_bytes: int,
    *,
    local_hosts: frozenset[str] | None = None,
    stranger_max_bytes: int = STRANGER_MAX_BYTES,
    compress: bool = True,
) -> None:
    """Serve ``dispatcher`` at ``path`` (POST) and ``path/ws`` (WebSocket).

    ``compress=False`` refuses the WebSocket's per-message deflate: a socket that carries
    media (the console's NavCam) would otherwise deflate every access unit (incompressible;
    aiohttp does it in a thread pool past 16 kB) on the way out and inflate it in the page.

    ``local_hosts`` makes the routes refuse (403) what a web page elsewhere could send through
    the operator's browser: a request whose ``Host`` is not one of these names (DNS
    rebinding) or whose ``Origin``, when present, is not this very server (cross-site POST,
    and WebSockets, which browsers do not hold to CORS). The station's local API needs it: it
    has no session of its own and can move the robot.
    """

    if OPEN_WEBSOCKETS not in app:
        app[OPEN_WEBSOCKETS] = set()
        app.on_shutdown.append(_close_websockets)

    def refused(request: web.Request) -> web.Response | None:
        if local_hosts is None:
            return None
        reason = browser_refusal(request.host, request.headers.get("Origin"), local_hosts)
        return None if reason is None else web.Response(status=403, text=reason)

    async def post(request: web.Request) -> web.Response:
        if (refusal := refused(request)) is not None:
            return refusal
        ctx = CallContext(peer_host=peer_host(request), transport="http")
        admission = request.app.get(ADMISSION)
        found = admission.slot_of(request.transport) if admission is not None else None
        limit = max_bytes
        if found is not None:
            _admitted(ctx, *found)
            if ctx.stranger:
                limit = min(limit, stranger_max_bytes)
        if request.content_length is not None and request.content_length > limit:
            return _too_large(f"{request.content_length} bytes", limit)
        try:
            async with asyncio.timeout(
                admission.limits.body_timeout if admission is not None else None
            ):
                body = (
                    await request.content.readexactly(request.content_length)
                    if request.content_length
                    else await _read_at_most(request.content, limit + 1)
                )
        except asyncio.IncompleteReadError:
            return web.Response(status=400, text="incomplete body")
        except TimeoutError:
            if found is not None:
                found[0].policy.counters["body_timeouts"] += 1
            # Answered, then closed at once: aiohttp would otherwise linger for the rest.
            response = web.Response(status=408, text="body not sent in time", headers=_CLOSE)
            await response.prepare(request)
            await response.write_eof()
            request.protocol.force_close()
            return response
        if len(body) > limit:
            return _too_large(f"more than {limit} bytes", limit)
        answer = await dispatcher.handle_bytes(body, ctx)
        if answer is None:
            return web.Response(status=204)
        status = 401 if _is_unauthorized(answer) else 200
        return web.Response(body=answer, status=status, content_type="application/json")

    async def websocket(request: web.Request) -> web.StreamResponse:
        if (refusal := refused(request)) is not None:
            return refusal
        ws = web.WebSocketResponse(max_msg_size=max_bytes, heartbeat=None, compress=compress)
        await ws.prepare(request)
        ctx = CallContext(peer_host=peer_host(request), transport="ws")
        ctx.extra["ws"] = ws
        admission = request.app.get(ADMISSION)
        found = admission.slot_of(request.transport) if admission is not None else None
        if found is not None:
            _admitted(ctx, *found)

        def broken() -> str:
            # A bug must cost one answer, never the station's connection.
            _LOGGER.exception("answering on the websocket of %s failed", ctx.peer_host)
            return encode_error(None, RpcError(INTERNAL_ERROR, "internal error")).decode()

        async def send(reply: str | None) -> None:
            if reply is not None and not ws.closed:
                try:
                    await ws.send_str(reply)
                except ConnectionError:
                    pass

        async def answer(incoming: Incoming) -> None:
            try:
                reply = await dispatcher.answer(incoming, ctx)
            except Exception:
                reply = broken()
            await send(reply)

        async def parse_then_answer(data: bytes | str) -> None:
            await answer(await dispatcher.parse_off_loop(data))

        # A request whose method may wait (a command waiting seconds for its actor) is answered
        # in its own task, owned by this connection, so it does not hold up the heartbeats
        # behind it; answers carry their ids and may come back out of order. Methods that
        # answer at once run inline, without a task or even a coroutine. Past the cap,
        # requests wait in line.
        in_flight: set[asyncio.Task[None]] = set()
        parsing: set[asyncio.Task[None]] = set()
        """The large message being parsed in a worker thread (at most one)."""
        loop = asyncio.get_running_loop()
        open_sockets = request.app[OPEN_WEBSOCKETS]
        open_sockets.add(ws)
        try:
            async for message in ws:
                kind = message.type
                if kind is aiohttp.WSMsgType.BINARY and "on_binary" in ctx.extra:
                    # A method made this socket carry media too (the console's push-to-talk).
                    ctx.extra["on_binary"](message.data)
                elif kind is aiohttp.WSMsgType.TEXT or kind is aiohttp.WSMsgType.BINARY:
                    if ctx.stranger and len(message.data) > stranger_max_bytes:
                        await send(_TOO_LARGE)  # not even parsed
                        continue
                    if (
                        len(message.data) > LARGE_MESSAGE_BYTES
                        and not parsing
                        and len(in_flight) < MAX_IN_FLIGHT_PER_SOCKET
                    ):
                        # Parsed in a worker thread while this socket's next requests (its
                        # heartbeats: a session must not time out behind its own map) go on;
                        # one at a time (a second waits here, reading stops: backpressure).
                        task = loop.create_task(parse_then_answer(message.data))
                        parsing.add(task)
                        task.add_done_callback(parsing.discard)
                        in_flight.add(task)
                        task.add_done_callback(in_flight.discard)
                        continue
                    incoming = await dispatcher.parse_off_loop(message.data)
                    if dispatcher.answers_at_once(incoming):
                        try:
                            reply = dispatcher.answer_at_once(incoming, ctx)
                        except Exception:
                            reply = broken()
                        if reply is not None and not ws.closed:
                            try:
                                await ws.send_str(reply)
                            except ConnectionError:
                                pass
                    elif len(in_flight) >= MAX_IN_FLIGHT_PER_SOCKET:
                        await answer(incoming)
                    else:
                        task = loop.create_task(answer(incoming))
                        in_flight.add(task)
                        task.add_done_callback(in_flight.discard)
                elif kind is aiohttp.WSMsgType.ERROR:
                    _LOGGER.debug("websocket error from %s: %s", ctx.peer_host, ws.exception())
        finally:
            open_sockets.discard(ws)
            for task in list(in_flight):
                task.cancel("websocket closed")
            await asyncio.gather(*in_flight, return_exceptions=True)
            for callback in ctx.extra.get("on_close", ()):
                callback()
        return ws

    app.router.add_post(path, post)
    app.router.add_get(path + "/ws", websocket)


def _admitted(ctx: CallContext, listener: AdmittingListener, slot: Slot) -> None:
    """``ctx`` is a call on ``slot``'s connection: a stranger's until a call has a session."""
    if not slot.has_session:
        ctx.stranger = True
        ctx.on_session = lambda: listener.policy.session_opened(slot)


ADMISSION = web.AppKey("admission", ServerAdmission)

OPEN_WEBSOCKETS: web.AppKey[set[web.WebSocketResponse]] = web.AppKey("open_websockets", set)
"""The RPC WebSockets open on an app, closed first when its server stops."""

SHUTDOWN_CLOSE_S = 0.2
"""How long a stopping server waits for its WebSocket peers to answer the close (the runner's
``shutdown_timeout``): a peer that does not answer costs no more than this."""


async def _close_websockets(app: web.Application) -> None:
    """Close each open WebSocket (1001 going away) as the server stops. Its peer learns at
    once, and its handler ends: otherwise aiohttp waits out its shutdown timeout twice for
    each (0.4 s a stop with a station connected), then cuts it without a close frame."""
    sockets = app[OPEN_WEBSOCKETS]
    if not sockets:
        return
    with contextlib.suppress(TimeoutError):
        async with asyncio.timeout(SHUTDOWN_CLOSE_S):
            await asyncio.gather(
                *(
                    ws.close(code=aiohttp.WSCloseCode.GOING_AWAY, message=b"stopping")
                    for ws in list(sockets)
                ),
                return_exceptions=True,
            )


@web.middleware
async def _track_requests(
    request: web.Request, handler: Callable[[web.Request], Awaitable[web.StreamResponse]]
) -> web.StreamResponse:
    """Tell the admission when a connection's request (a WebSocket's whole life) is under
    way: its header and idle timeouts apply between requests."""
    found = request.app[ADMISSION].slot_of(request.transport)
    if found is None:
        return await handler(request)
    listener, slot = found
    listener.policy.request_started(slot)
    try:
        return await handler(request)
    finally:
        listener.policy.request_ended(slot, listener.loop.time())


class WebServer(Actor):
    """Owns a bound aiohttp runner and its admitting listeners: checks their connections'
    timeouts while it runs; stops accepting and cleans up (connections closed) when the
    daemon stops."""

    restart = False

    def __init__(
        self,
        bus: Bus,
        runner: web.AppRunner,
        name: str,
        listeners: Sequence[AdmittingListener] = (),
    ) -> None:
        super().__init__(bus)
        self.runner = runner
        self.name = name
        self.listeners = list(listeners)

    async def run(self) -> None:
        try:
            async with asyncio.TaskGroup() as sweepers:
                for listener in self.listeners:
                    sweepers.create_task(listener.sweep(), name=f"admission:{self.name}")
                await wait_forever()
        finally:
            for listener in self.listeners:
                listener.close()
            with contextlib.suppress(Exception):
                await asyncio.shield(self.runner.cleanup())


async def serve_app(
    app: web.Application,
    host: str,
    port: int,
    *,
    supervisor: Supervisor,
    bus: Bus,
    name: str,
    limits: AdmissionLimits = TRUSTED,
) -> int:
    """Bind ``app`` on ``host:port`` (0: the kernel chooses), hand it to a supervised
    :class:`WebServer`, and return the bound port. A port in use raises ``OSError``."""
    ports = await serve_app_sites(
        app, host, port, supervisor=supervisor, bus=bus, name=name, limits=limits
    )
    return ports[0]


async def serve_app_sites(
    app: web.Application,
    host: str,
    port: int,
    *,
    supervisor: Supervisor,
    bus: Bus,
    name: str,
    tls_sites: Sequence[tuple[str, int, ssl.SSLContext]] = (),
    limits: AdmissionLimits = TRUSTED,
) -> list[int]:
    """:func:`serve_app`, and also on each of ``tls_sites`` over TLS (one runner): the bound
    ports, plain first. Every port admits connections by ``limits``
    (:mod:`brasidas.admission`; a TLS handshake within ``header_timeout``)."""
    admission = ServerAdmission(limits)
    app[ADMISSION] = admission
    app.middlewares.append(_track_requests)
    runner = web.AppRunner(
        app,
        access_log=None,
        handle_signals=False,
        shutdown_timeout=SHUTDOWN_CLOSE_S,
        keepalive_timeout=limits.idle_timeout,
    )
    await runner.setup()
    factory: Callable[[], asyncio.Protocol] = runner.server  # type: ignore[assignment]
    listeners: list[AdmittingListener] = []
    try:
        for site_host, site_port, context in [(host, port, None), *tls_sites]:
            listeners.append(
                AdmittingListener(
                    _listening_socket(site_host, site_port),
                    factory,
                    AdmissionPolicy(limits),
                    name if context is None else f"{name} (TLS)",
                    ssl=context,
                )
            )
    except OSError:
        for listener in listeners:
            listener.sock.close()
        await runner.cleanup()
        raise
    for listener in listeners:
        listener.start()
    if listeners and (shortfall := listeners[0].policy.capacity_shortfall()) is not None:
        _LOGGER.warning("%s: %s", name, shortfall)
    admission.listeners += listeners
    supervisor.start(WebServer(bus, runner, name, listeners))
    return [int(listener.sock.getsockname()[1]) for listener in listeners]


def _listening_socket(host: str, port: int) -> socket.socket:
    """A bound, listening TCP socket (as aiohttp's TCPSite makes one); ``OSError`` when the
    port is in use."""
    info = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    family, kind, proto, _, address = info[0]
    sock = socket.socket(family, kind, proto)
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        sock.bind(address)
        sock.listen(LISTEN_BACKLOG)
    except OSError:
        sock.close()
        raise
    return sock


async def _read_at_most(stream: aiohttp.StreamReader, limit: int) -> bytes:
    """A body of unknown length (chunked), read until its end or ``limit`` bytes."""
    body = bytearray()
    while len(body) < limit and not stream.at_eof():
        chunk = await stream.read(limit - len(body))
        if not chunk:
            break
        body += chunk
    return bytes(body)


LISTEN_BACKLOG = 1024
"""Room in the kernel for a burst of connections (a station's among a stranger's), each
accepted and, past the caps, closed at once."""

_CLOSE = {"Connection": "close"}
_TOO_LARGE = encode_error(None, RpcError(REQUEST_TOO_LARGE, "request too large")).decode()


def _too_large(size: str, limit: int) -> web.Response:
    """413, saying the request's size and the limit (a map or route too big for one call)."""
    message = f"request too large: {size}, the limit is {limit} bytes"
    body = encode_error(None, RpcError(REQUEST_TOO_LARGE, message))
    return web.Response(status=413, body=body, content_type="application/json")


def _is_unauthorized(answer: bytes) -> bool:
    try:
        message = decode(answer)
    except (ValueError, RecursionError):
        return False
    error = message.get("error") if isinstance(message, dict) else None
    return isinstance(error, dict) and error.get("code") == UNAUTHORIZED


def peer_host(request: web.Request) -> str:
    """The address an HTTP or WebSocket request came from ("" if unknown)."""
    peer = request.transport.get_extra_info("peername") if request.transport else None
    return str(peer[0]) if peer else ""


class RpcClient:
    """A JSON-RPC client over one WebSocket. ``close()`` is idempotent and fails pending calls.

    One task at a time receives from the socket (aiohttp allows no more), and every received
    answer goes to its call whoever reads it. A caller that finds nobody reading reads its own
    answer (the fast path, as a bare ``send``/``receive`` would: no other task on the way, no
    extra loop turn) and hands answers to others' calls on the way. Otherwise, and whenever
    no call reads, the reader task does: it answers the calls of callers that wait, notices
    the connection's end while idle, and drops unsolicited messages. After each message it
    delivers, the reader lets the woken callers run first, so a caller's next call (the usual
    back-to-back pattern) takes the fast path; a call made while the reader is parked in
    ``receive`` (after an idle spell) is answered through it, one loop turn later.
    """

    def __init__(self, url: str, *, timeout: float = 3.0) -> None:
        self.url = url
        self.timeout = timeout
        self._session: aiohttp.ClientSession | None = None
        self._ws: aiohttp.ClientWebSocketResponse | None = None
        self._reader: asyncio.Task[None] | None = None
        self._pending: dict[int, tuple[asyncio.Future[Any], float, str, float]] = {}
        """Calls waiting for their answer: future, deadline (loop time), method, time limit."""
        self._expiry: asyncio.TimerHandle | None = None
        """One timer for every pending call, at the earliest deadline (none per call)."""
        self._receiving: asyncio.Task[Any] | None = None
        """The task inside ``ws.receive()``: the reader task, or a caller on the fast path."""
        self._awaited: asyncio.Future[Any] | None = None
        """The answer the fast-path caller in ``_receiving`` reads for."""
        self._timed_out = False
        """The expiry timer cancelled the fast-path caller's ``receive`` (its call timed out)."""
        self._reader_parked: asyncio.Future[None] | None = None
        """The reader task waits on this while a caller reads."""
        self._resume: asyncio.TimerHandle | None = None
        """When the reader receives again after a fast-path call (unless a caller does)."""
        self._ids = itertools.count(1)
        self.closed = asyncio.Event()
        self.bad_answers = 0
        """Received messages (or items of a batch) that answer nothing valid: dropped."""

    async def open(self) -> None:
        self._session = aiohttp.ClientSession()
        try:
            self._ws = await self._session.ws_connect(
                self.url,
                timeout=aiohttp.ClientWSTimeout(ws_close=1.0),
                autoping=True,
                max_msg_size=ANSWER_MAX_BYTES,  # get_map's answer carries the whole map
            )
        except BaseException:
            await self._session.close()
            self._session = None
            raise
        self._reader = asyncio.get_running_loop().create_task(
            self._read(), name=f"rpc-client:{self.url}"
        )

    async def call(
        self,
        method: str,
        params: dict[str, Any] | list[Any] | EncodedParams | None = None,
        *,
        timeout: float | None = None,
    ) -> Any:
        """Call ``method``; raises :class:`RpcError` for an error answer or a timeout."""
        ws = self._ws
        if ws is None or ws.closed:
            raise ConnectionError(f"not connected to {self.url}")
        request_id = next(self._ids)
        loop = asyncio.get_running_loop()
        future: asyncio.Future[Any] = loop.create_future()
        limit = timeout or self.timeout
        deadline = loop.time() + limit
        self._pending[request_id] = (future, deadline, method, limit)
        expiry = self._expiry
        if expiry is None or deadline < expiry.when():
            if expiry is not None:
                expiry.cancel()
            self._expiry = loop.call_at(deadline, self._expire)
        try:
            text = request_text(method, params, request_id)
            if len(text) > MAP_REQUEST_MAX_BYTES:
                # The platform's socket would close on it (and end the session): refuse here.
                raise RpcError(
                    REQUEST_TOO_LARGE,
                    f"request too large: {len(text)} bytes, the limit is "
                    f"{MAP_REQUEST_MAX_BYTES} bytes",
                )
            await ws.send_str(text)
            if self._receiving is None:
                return await self._read_own(ws, future)
            return await future
        finally:
            del self._pending[request_id]

    async def _read_own(
        self, ws: aiohttp.ClientWebSocketResponse, future: asyncio.Future[Any]
    ) -> Any:
        """The fast path: receive until ``future`` has its answer (or fails), then hand
        receiving back to the reader task (unless the next call takes it first)."""
        task = asyncio.current_task()
        assert task is not None
        self._receiving, self._awaited = task, future
        try:
            while not future.done():
                try:
                    message = await ws.receive()
                except asyncio.CancelledError:
                    if self._timed_out and future.done() and task.uncancel() == 0:
                        break  # only the expiry timer's doing: the call timed out
                    raise
                if not self._received(message):
                    self._ended()
        finally:
            self._receiving = self._awaited = None
            self._timed_out = False
            if len(self._pending) > 1:
                self._resume_reader()  # others' answers are due: the reader receives them
            elif self._resume is None:
                self._resume = asyncio.get_running_loop().call_later(
                    READER_RESUME_DELAY, self._resume_reader
                )
        return future.result()

    def _resume_reader(self) -> None:
        """The reader receives again, unless a caller does."""
        if self._resume is not None:
            self._resume.cancel()
            self._resume = None
        parked = self._reader_parked
        if self._receiving is None and parked is not None and not parked.done():
            parked.set_result(None)

    def _expire(self) -> None:
        """Fail the calls past their deadline; set the timer for the next one."""
        self._expiry = None
        loop = asyncio.get_running_loop()
        now = loop.time() + 0.001  # a timer may run up to the clock's resolution early
        following = None
        for future, deadline, method, limit in self._pending.values():
            if future.done():
                continue
            if deadline <= now:
                message = f"no answer to {method} within {limit:.1f} s"
                future.set_exception(RpcError(TIMEOUT, message))
            elif following is None or deadline < following:
                following = deadline
        awaited, reading = self._awaited, self._receiving
        if awaited is not None and awaited.done() and reading is not None and not self._timed_out:
            self._timed_out = True  # the fast-path caller waits in receive(): wake it
            reading.cancel("rpc call timed out")
        if following is not None:
            self._expiry = loop.call_at(following, self._expire)

    async def _read(self) -> None:
        """The reader task: receives whenever no caller does, until the connection ends."""
        ws = self._ws
        assert ws is not None
        task = asyncio.current_task()
        loop = asyncio.get_running_loop()
        try:
            while True:
                if self._receiving is not None:
                    self._reader_parked = parked = loop.create_future()
                    try:
                        await parked
                    finally:
                        self._reader_parked = None
                    continue
                self._receiving = task
                try:
                    message = await ws.receive()
                finally:
                    self._receiving = None
                if not self._received(message):
                    return
                # The callers just answered run first: a next call may read for itself.
                await asyncio.sleep(0)
        finally:
            self._ended()

    def _received(self, message: aiohttp.WSMessage) -> bool:
        """Handle one received message; False when it says the connection has ended."""
        kind = message.type
        if kind is aiohttp.WSMsgType.TEXT or kind is aiohttp.WSMsgType.BINARY:
            self.feed(message.data)
            return True
        return kind not in _CONNECTION_ENDED

    def _ended(self) -> None:
        self._fail_pending(ConnectionError(f"connection to {self.url} closed"))
        self.closed.set()

    def feed(self, data: bytes | str) -> None:
        """Resolve the calls a received message answers. What is not a valid answer to one
        of ours is counted in ``bad_answers`` and dropped (a call it names fails at once)."""
        try:
            message = decode_answer_message(data)
        except (ValueError, RecursionError) as err:
            self._bad_answer(f"unparseable ({err})")
            return
        if (
            type(message) is dict
            and type(request_id := message.get("id")) is int
            and "result" in message
            and "error" not in message
        ):
            # The usual message, one result to a call of ours: read_answer's checks, inline
            # (this runs once per heartbeat, and a call less shows in its round trip).
            pending = self._pending.get(request_id)
            if pending is not None and not (future := pending[0]).done():
                future.set_result(message["result"])
            return
        for item in message if type(message) is list else (message,):
            try:
                answer = read_answer(item)
            except BadAnswer as err:
                self._bad_answer(str(err), err.request_id)
                continue
            pending = self._pending.get(answer.request_id)
            if pending is None or (future := pending[0]).done():
                continue  # answered after its call gave up
            if answer.error is not None:
                future.set_exception(answer.error)
            else:
                future.set_result(answer.result)

    def _bad_answer(self, reason: str, request_id: int | None = None) -> None:
        self.bad_answers += 1
        level = logging.WARNING if self.bad_answers == 1 else logging.DEBUG  # no log flood
        _LOGGER.log(level, "bad answer from %s: %s (%d so far)", self.url, reason, self.bad_answers)
        pending = self._pending.get(request_id) if request_id is not None else None
        if pending is not None and not (future := pending[0]).done():
            future.set_exception(RpcError(INTERNAL_ERROR, f"malformed answer: {reason}"))

    def _fail_pending(self, exc: Exception) -> None:
        """Fail every pending call (the connection is ending): no timer is left behind."""
        for timer in (self._expiry, self._resume):
            if timer is not None:
                timer.cancel()
        self._expiry = self._resume = None
        for future, *_ in self._pending.values():
            if not future.done():
                future.set_exception(exc)

    async def close(self) -> None:
        self._fail_pending(ConnectionError("client closed"))
        if self._ws is not None:
            with contextlib.suppress(Exception):
                await self._ws.close()
        if self._reader is not None:
            self._reader.cancel("client closed")
            with contextlib.suppress(asyncio.CancelledError, Exception):
                await self._reader
            self._reader = None
        if self._session is not None:
            await self._session.close()
            self._session = None
        self.closed.set()

    async def __aenter__(self) -> RpcClient:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()
