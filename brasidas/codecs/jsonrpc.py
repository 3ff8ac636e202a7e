"""JSON-RPC 2.0: a sans-IO dispatcher. Transports hand it bytes and send back what it returns.

Supports single calls, batches and notifications, and answers the standard errors:
-32700 parse error, -32600 invalid request, -32601 method not found, -32602 invalid params,
-32603 internal error; plus the application's codes below (docs/reference/protocol.md).
"""

from __future__ import annotations

import asyncio
import inspect
import json
import json.decoder
import json.scanner
import logging
import math
import re
from collections.abc import Callable
from dataclasses import dataclass, field
from json.encoder import encode_basestring_ascii
from typing import Any

import orjson

_LOGGER = logging.getLogger(__name__)

PARSE_ERROR = -32700
INVALID_REQUEST = -32600
METHOD_NOT_FOUND = -32601
INVALID_PARAMS = -32602
INTERNAL_ERROR = -32603
UNAUTHORIZED = -32001
UNAVAILABLE = -32002
"""The method exists but what it needs is not on this platform (no camera, ...)."""
TIMEOUT = -32003
"""No answer within the caller's limit: raised by the client itself (a platform never answers
it; the station's local API passes on its own calls' timeouts)."""
REQUEST_TOO_LARGE = -32004
CONTROL_REFUSED = -32005
"""A control method refused to an observer: another station holds control (the message names
it). Not a timeout: the platform answered, and retrying will not help until control changes."""


class RpcError(Exception):
    """Raised by a method to answer a JSON-RPC error."""

    def __init__(self, code: int, message: str, data: Any = None) -> None:
        super().__init__(message)
        self.code = code
        self.message = message
        self.data = data

    def as_dict(self) -> dict[str, Any]:
        error: dict[str, Any] = {"code": self.code, "message": self.message}
        if self.data is not None:
            error["data"] = self.data
        return error


class Unauthorized(RpcError):
    def __init__(self, message: str = "unauthorized") -> None:
        super().__init__(UNAUTHORIZED, message)


@dataclass
class CallContext:
    """Who is calling: filled by the transport, extended by the authorizer."""

    peer_host: str = ""
    transport: str = ""
    session: Any = None
    """Set by the authorizer for methods that need a session."""
    extra: dict[str, Any] = field(default_factory=dict)
    stranger: bool = False
    """The connection has no session yet: a batch may hold only methods that need none."""
    on_session: Callable[[], None] | None = None
    """Called (by :meth:`session_opened`) when the stranger's connection gets a session."""

    def session_opened(self) -> None:
        """A call on this connection has a session (authorized, or ``connect`` opened one)."""
        if self.stranger:
            self.stranger = False
            if self.on_session is not None:
                self.on_session()


Handler = Callable[..., Any]
"""``handler(ctx, **params)``: a plain function answers at once; a coroutine function may wait
(on another actor, the network) and transports then answer it without holding up others."""
Authorizer = Callable[[CallContext, dict[str, Any]], None]
UnparsedCheck = Callable[[str], str | None]
"""A large request's text, unparsed: why it is refused (without parsing it), or None."""
"""Checks (and strips) credentials from by-name params before a session method runs."""


_SIMPLE_TYPES = {"str": str, "int": int, "float": float, "bool": bool}


@dataclass
class Method:
    name: str
    handler: Handler
    session_required: bool
    signature: inspect.Signature
    names: frozenset[str] = frozenset()
    required: frozenset[str] = frozenset()
    types: dict[str, type] = field(default_factory=dict)
    """Simple JSON types to check, from the handler's annotations (str, int, float, bool)."""
    waits: bool = True
    """The handler is a coroutine function: answering may take a while."""

    @classmethod
    def build(cls, name: str, handler: Handler, session_required: bool) -> Method:
        signature = inspect.signature(handler)
        params = list(signature.parameters.values())[1:]  # drop the call context
        types: dict[str, type] = {}
        for param in params:
            annotation = param.annotation
            if isinstance(annotation, str):
                annotation = _SIMPLE_TYPES.get(annotation)
            if annotation in (str, int, float, bool):
                types[param.name] = annotation
        return cls(
            name,
            handler,
            session_required,
            signature.replace(parameters=params),
            frozenset(p.name for p in params),
            frozenset(p.name for p in params if p.default is inspect.Parameter.empty),
            types,
            inspect.iscoroutinefunction(handler),
        )

    async def invoke(self, ctx: CallContext, **params: Any) -> Any:
        result = self.handler(ctx, **params)
        return await result if self.waits else result


@dataclass(slots=True)
class Incoming:
    """A received message, decoded (``message``) or not (``parse_error`` is its answer)."""

    message: Any = None
    parse_error: str | None = None


@dataclass(slots=True)
class _Call:
    """A request that passed every check: what remains is to run its handler."""

    request_id: Any
    notification: bool
    method: Method
    kwargs: dict[str, Any]


MAX_BATCH = 100
"""Requests in a batch, at most: a longer one is answered with one error (no fan-out)."""
MAX_ANSWER_BYTES = 1 << 20
"""An answer longer than this is replaced by an error (-32603)."""


class Dispatcher:
    """Method table and the JSON-RPC envelope logic."""

    def __init__(
        self,
        authorizer: Authorizer | None = None,
        *,
        max_batch: int = MAX_BATCH,
        max_answer_bytes: int = MAX_ANSWER_BYTES,
    ) -> None:
        self._methods: dict[str, Method] = {}
        self.authorizer = authorizer
        self.max_batch = max_batch
        self.max_answer_bytes = max_answer_bytes
        self.counters: dict[str, int] = {
            "calls": 0,
            "parse_errors": 0,
            "invalid_requests": 0,
            "unknown_methods": 0,
            "invalid_params": 0,
            "unauthorized": 0,
            "internal_errors": 0,
            "refused_batches": 0,
            "answers_too_large": 0,
            "refused_unparsed": 0,
        }
        self._unparsed_checks: dict[str, UnparsedCheck] = {}

    def add(
        self, name: str, handler: Handler, *, session_required: bool = True
    ) -> Callable[[], None]:
        """Register ``handler(ctx, **params)``; returns the function that removes it."""
        if name in self._methods:
            raise ValueError(f"method {name} already registered")
        self._methods[name] = Method.build(name, handler, session_required)
        return lambda: self._methods.pop(name, None)  # type: ignore[return-value]

    def check_unparsed(self, name: str, check: UnparsedCheck) -> None:
        """A request for ``name`` over :data:`LARGE_MESSAGE_BYTES` goes to ``check(text)`` (in
        a worker thread) before it is parsed: a refusal is answered INVALID_PARAMS with it, and
        the message is never parsed (a 150,001-vertex map costs a scan, not 20 MB of lists)."""
        self._unparsed_checks[name] = check

    def has(self, name: str) -> bool:
        return name in self._methods

    async def call_local(self, name: str, **params: Any) -> Any:
        """Call a method in-process, as a trusted caller (no session check)."""
        return await self._methods[name].invoke(CallContext(transport="local"), **params)

    @property
    def method_names(self) -> list[str]:
        return sorted(self._methods)

    async def handle_bytes(self, data: bytes | str, ctx: CallContext) -> bytes | None:
        """Answer one JSON-RPC message (single or batch); None when nothing is to be sent.
        A large one is read off the loop (:meth:`parse_off_loop`)."""
        answer = await self.answer(await self.parse_off_loop(data), ctx)
        return None if answer is None else answer.encode()

    async def parse_off_loop(self, data: bytes | str) -> Incoming:
        """:meth:`parse`; a message over :data:`LARGE_MESSAGE_BYTES` in a worker thread with
        the pure-Python parser, which lets the loop take the GIL every few milliseconds (the C
        parser holds it for the whole document: 0.2-0.6 s for a 3 MB map, enough to trip the
        0.3 s deadman of a station driving meanwhile). A file's text in one escaped string
        (the console's imports) is quick for the C parser (35 ms for 4.5 MB) and slow for
        Python's (0.75 s): :func:`escape_heavy` messages keep :meth:`parse`."""
        if len(data) <= LARGE_MESSAGE_BYTES:
            return self.parse(data)
        if self._unparsed_checks:
            refused = await self._refused_unparsed(data)
            if refused is not None:
                return refused
        if escape_heavy(data):
            return self.parse(data)
        return await asyncio.to_thread(self.parse, data, interruptible=True)

    async def _refused_unparsed(self, data: bytes | str) -> Incoming | None:
        """The refusal of a large request its method's unparsed check gives, or None."""
        head = request_head(data)
        check = self._unparsed_checks.get(head[1]) if head is not None else None
        if head is None or check is None:
            return None
        text = data if isinstance(data, str) else _text(data)
        refusal = await asyncio.to_thread(check, text)
        if refusal is None:
            return None
        self.counters["refused_unparsed"] += 1
        error = RpcError(INVALID_PARAMS, refusal)
        return Incoming(None, _encode(_error_response(head[0], error)))

    def parse(self, data: bytes | str, *, interruptible: bool = False) -> Incoming:
        """Decode a message; what cannot be decoded already carries its parse-error answer.
        ``interruptible``: the pure-Python parser (from a worker thread)."""
        try:
            if interruptible:
                text = data if isinstance(data, str) else _text(data)
                return Incoming(_INTERRUPTIBLE_DECODER.decode(text))
            return Incoming(decode(data))
        except (ValueError, RecursionError) as err:
            # RecursionError: "[[[[…", nested deeper than the parser's stack.
            self.counters["parse_errors"] += 1
            error = RpcError(PARSE_ERROR, f"parse error: {err}")
            return Incoming(None, _encode(_error_response(None, error)))

    def answers_at_once(self, incoming: Incoming) -> bool:
        """True when answering cannot wait on anything: a parse error, or a single request
        for an unknown method or one whose handler is a plain function. Transports answer
        these inline (:meth:`answer_at_once`) and give the rest a task of their own."""
        if incoming.parse_error is not None:
            return True
        message = incoming.message
        if type(message) is not dict:
            return type(message) is not list  # a batch may hold a method that waits
        name = message.get("method")
        method = self._methods.get(name) if type(name) is str else None
        return method is None or not method.waits

    def answer_at_once(self, incoming: Incoming, ctx: CallContext) -> str | None:
        """The encoded answer to a message :meth:`answers_at_once` accepted, without a
        coroutine in the way; None when nothing is to be sent."""
        if incoming.parse_error is not None:
            return incoming.parse_error
        message = incoming.message
        if (
            type(message) is dict
            and type(request_id := message.get("id")) is int
            and message.get("jsonrpc") == "2.0"
            and type(name := message.get("method")) is str
            and type(params := message.get("params")) is dict
            and (method := self._methods.get(name)) is not None
        ):
            # The usual request (a heartbeat, every call of every session): _begin's,
            # _prepare's and _run_now's checks in one go, without their intermediate objects.
            self.counters["calls"] += 1
            try:
                self._check(method, params, ctx)
                result = method.handler(ctx, **params)
            except Exception as err:
                response = self._failed(request_id, False, name, err)
                return None if response is None else self._encode_response(response)
            return self._encode_response(_result(request_id, result))
        call = self._begin(message, ctx)
        response = self._run_now(call, ctx) if isinstance(call, _Call) else call
        return None if response is None else self._encode_response(response)

    async def answer(self, incoming: Incoming, ctx: CallContext) -> str | None:
        """The encoded answer to a parsed message; None when nothing is to be sent."""
        if incoming.parse_error is not None:
            return incoming.parse_error
        message = incoming.message
        if type(message) is list:
            if not message:
                self.counters["invalid_requests"] += 1
                return _encode(_error_response(None, RpcError(INVALID_REQUEST, "empty batch")))
            if (refusal := self._refused_batch(message, ctx)) is not None:
                self.counters["refused_batches"] += 1
                return _encode(_error_response(None, RpcError(INVALID_REQUEST, refusal)))
            responses = [await self.handle_message(item, ctx) for item in message]
            answered = [item for item in responses if item is not None]
            if not answered:
                return None
            try:
                text = _encode(answered)
            except (ValueError, TypeError, RecursionError):
                text = "[" + ",".join(self._encode_response(item) for item in answered) + "]"
            return self._bounded(None, text)
        response = await self.handle_message(message, ctx)
        return self._encode_response(response) if response is not None else None

    def _refused_batch(self, batch: list[Any], ctx: CallContext) -> str | None:
        """Why ``batch`` is answered with one error, or None: longer than ``max_batch``, or
        from a stranger and holding anything but calls of methods that need no session."""
        if len(batch) > self.max_batch:
            return f"batch of {len(batch)} requests refused (at most {self.max_batch})"
        if ctx.stranger:
            for item in batch:
                name = item.get("method") if type(item) is dict else None
                if type(name) is not str:
                    continue  # not a request: answered -32600 on its own, as the spec says
                method = self._methods.get(name)
                if method is None or method.session_required:
                    return "before a session, a batch may hold only calls that need none"
        return None

    def _bounded(self, request_id: Any, text: str) -> str:
        """``text``, or an error in its place when it is longer than ``max_answer_bytes``."""
        if len(text) <= self.max_answer_bytes:
            return text
        self.counters["answers_too_large"] += 1
        error = RpcError(INTERNAL_ERROR, f"answer too large ({len(text)} bytes)")
        return _encode(_error_response(request_id, error))

    def _encode_response(self, response: dict[str, Any]) -> str:
        """Encoded; a result JSON cannot hold (NaN, an object) is answered -32603 instead."""
        try:
            if "result" in response:
                # The envelope by hand: only the result goes through the encoder (the fixed
                # keys would cost as much again, per answer).
                text = f'{{"jsonrpc":"2.0","id":{_encode_id(response["id"])},"result":{_encode(response["result"])}}}'
                return self._bounded(response["id"], text)
            return _encode(response)
        except (ValueError, TypeError, RecursionError) as err:
            self.counters["internal_errors"] += 1
            _LOGGER.error("result of a call cannot be sent as JSON: %s", err)
            error = RpcError(INTERNAL_ERROR, f"internal error: result is not valid JSON ({err})")
            return _encode(_error_response(response.get("id"), error))

    async def handle_message(self, message: Any, ctx: CallContext) -> dict[str, Any] | None:
        """Answer one decoded request object (its params are consumed); None for a
        notification."""
        call = self._begin(message, ctx)
        if not isinstance(call, _Call):
            return call
        if not call.method.waits:
            return self._run_now(call, ctx)
        try:
            result = await call.method.handler(ctx, **call.kwargs)
        except Exception as err:
            return self._failed(call.request_id, call.notification, call.method.name, err)
        return None if call.notification else _result(call.request_id, result)

    def _run_now(self, call: _Call, ctx: CallContext) -> dict[str, Any] | None:
        try:
            result = call.method.handler(ctx, **call.kwargs)
        except Exception as err:
            return self._failed(call.request_id, call.notification, call.method.name, err)
        return None if call.notification else _result(call.request_id, result)

    def _begin(self, message: Any, ctx: CallContext) -> _Call | dict[str, Any] | None:
        """Envelope, method, session and params checked: the call to run, or its answer
        already (an error, or None for a notification that failed)."""
        if type(message) is not dict or message.get("jsonrpc") != "2.0":
            self.counters["invalid_requests"] += 1
            request_id = message.get("id") if type(message) is dict else None
            return _error_response(
                _valid_id(request_id), RpcError(INVALID_REQUEST, "invalid request")
            )
        notification = "id" not in message
        request_id = message.get("id")
        if not notification and not _is_valid_id(request_id):
            self.counters["invalid_requests"] += 1
            return _error_response(None, RpcError(INVALID_REQUEST, "invalid id"))
        name = message.get("method")
        params = message.get("params", {})
        if type(name) is not str or not isinstance(params, dict | list):
            self.counters["invalid_requests"] += 1
            return _error_response(request_id, RpcError(INVALID_REQUEST, "invalid request"))
        self.counters["calls"] += 1
        try:
            method, kwargs = self._prepare(name, params, ctx)
        except Exception as err:
            return self._failed(request_id, notification, name, err)
        return _Call(request_id, notification, method, kwargs)

    def _failed(
        self, request_id: Any, notification: bool, name: str, err: Exception
    ) -> dict[str, Any] | None:
        if not isinstance(err, RpcError):
            self.counters["internal_errors"] += 1
            _LOGGER.error("method %s failed", name, exc_info=err)
            err = RpcError(INTERNAL_ERROR, "internal error")
        return None if notification else _error_response(request_id, err)

    def _check_params(self, method: Method, kwargs: dict[str, Any]) -> None:
        """Names and simple JSON types, from what was cached when the method was added."""
        problem = ""
        if not method.names.issuperset(kwargs):
            problem = f"unexpected {sorted(set(kwargs) - method.names)}"
        elif not method.required.issubset(kwargs):
            problem = f"missing {sorted(method.required - set(kwargs))}"
        else:
            for name, expected in method.types.items():
                value = kwargs.get(name)
                if name not in kwargs or _json_type_ok(value, expected):
                    continue
                problem = f"'{name}' must be " + (
                    "a finite number"
                    if expected is float
                    else "Unicode text (no lone surrogate)"
                    if isinstance(value, str)
                    else expected.__name__
                )
                break
        if problem:
            self.counters["invalid_params"] += 1
            raise RpcError(INVALID_PARAMS, f"invalid params: {problem}")

    def _prepare(
        self, name: str, params: dict[str, Any] | list[Any], ctx: CallContext
    ) -> tuple[Method, dict[str, Any]]:
        """The method and its by-name params, authorized and checked."""
        method = self._methods.get(name)
        if method is None:
            self.counters["unknown_methods"] += 1
            raise RpcError(METHOD_NOT_FOUND, f"method not found: {name}")
        if type(params) is list:
            try:
                kwargs = method.signature.bind(*params).arguments
            except TypeError as err:
                self.counters["invalid_params"] += 1
                raise RpcError(INVALID_PARAMS, f"invalid params: {err}") from None
        else:
            kwargs = params  # type: ignore[assignment]  # decoded for this call alone
        self._check(method, kwargs, ctx)
        return method, kwargs

    def _check(self, method: Method, kwargs: dict[str, Any], ctx: CallContext) -> None:
        """The session (stripped from ``kwargs``) and the params of a call of ``method``."""
        if method.session_required:
            if self.authorizer is None:
                raise RpcError(INTERNAL_ERROR, "no authorizer")
            try:
                self.authorizer(ctx, kwargs)
            except RpcError as err:
                if err.code == UNAUTHORIZED:
                    self.counters["unauthorized"] += 1
                raise
            ctx.session_opened()
        if kwargs or method.required:
            self._check_params(method, kwargs)


def _json_type_ok(value: Any, expected: type) -> bool:
    if isinstance(value, bool):
        return expected is bool
    if expected is float:
        return isinstance(value, int) or (isinstance(value, float) and math.isfinite(value))
    if expected is str:
        return isinstance(value, str) and (value.isascii() or _is_unicode(value))
    return isinstance(value, expected)


def _is_unicode(text: str) -> bool:
    """No lone surrogate (``"\\ud800"`` decodes to one): the text can be encoded."""
    try:
        text.encode()
    except UnicodeEncodeError:
        return False
    return True


def _is_valid_id(value: Any) -> bool:
    kind = type(value)
    return value is None or kind is str or kind is int or (kind is float and math.isfinite(value))


def _valid_id(value: Any) -> Any:
    return value if _is_valid_id(value) else None


def _error_response(request_id: Any, err: RpcError) -> dict[str, Any]:
    return {"jsonrpc": "2.0", "id": request_id, "error": err.as_dict()}


def _result(request_id: Any, result: Any) -> dict[str, Any]:
    return {"jsonrpc": "2.0", "id": request_id, "result": result}


def _refuse_constant(name: str) -> Any:
    raise ValueError(f"{name} is not JSON")


# One decoder and one encoder for every message: json.loads/dumps with non-default options
# build a new one per call. NaN and Infinity are not JSON: refused both ways.
_DECODER = json.JSONDecoder(parse_constant=_refuse_constant)
_ENCODER = json.JSONEncoder(separators=(",", ":"), allow_nan=False)
_INTERRUPTIBLE_DECODER = json.JSONDecoder(parse_constant=_refuse_constant)
"""The same, its walk over values in Python (bytecode: the GIL changes hands every few ms)
and each string read in C: Python's own string reader runs one regex over a long string with
the GIL held (a file's 3 MB text: 0.2-0.6 s), C's reads it in a few milliseconds."""
_INTERRUPTIBLE_DECODER.parse_string = (  # type: ignore[attr-defined]
    json.decoder.c_scanstring or json.decoder.py_scanstring  # type: ignore[attr-defined]
)
_INTERRUPTIBLE_DECODER.scan_once = json.scanner.py_make_scanner(_INTERRUPTIBLE_DECODER)  # type: ignore[attr-defined]


_HEAD_OPEN = re.compile(rb"\s*\{")
_HEAD_MEMBER = re.compile(
    rb'\s*"(jsonrpc|id|method)"\s*:\s*("[A-Za-z0-9_.:-]{0,64}"|-?\d{1,15})\s*,'
)
_TAIL_ID = re.compile(rb',\s*"id"\s*:\s*(-?\d{1,15}|"[A-Za-z0-9_.:-]{0,64}")\s*\}\s*$')
HEAD_BYTES = 256
"""How far into a message (and back from its end) :func:`request_head` reads."""


def request_head(data: bytes | str) -> tuple[int | str, str] | None:
    """A single request's id and method read without parsing it: from the members before its
    first non-scalar one (``{"jsonrpc":"2.0","method":"m",...``) and an id that closes the
    message (``...,"id":7}``, as clients here send it) or leads it; None when not so plain."""
    head = data[:HEAD_BYTES]
    tail = data[-HEAD_BYTES:]
    if isinstance(head, str):
        head = head.encode("utf-8", "surrogatepass")
        tail = tail.encode("utf-8", "surrogatepass")  # type: ignore[union-attr]
    assert isinstance(tail, bytes)
    opened = _HEAD_OPEN.match(head)
    if opened is None:
        return None
    members: dict[bytes, bytes] = {}
    position = opened.end()
    while (member := _HEAD_MEMBER.match(head, position)) is not None:
        members[member[1]] = member[2]
        position = member.end()
    closing = _TAIL_ID.search(tail)
    token = members.get(b"id", closing[1] if closing is not None else None)
    method = members.get(b"method")
    if token is None or method is None or members.get(b"jsonrpc") != b'"2.0"':
        return None
    request_id = json.loads(token)
    return (request_id, json.loads(method)) if type(request_id) in (int, str) else None


def escape_heavy(data: bytes | str) -> bool:
    """Mostly escaped text (a file's lines), not many small values (a map's numbers): the
    C parser's time grows with the values, the pure-Python one's with the escapes."""
    if isinstance(data, str):
        return data.count("\\") * 4 > data.count(",")
    return data.count(b"\\") * 4 > data.count(b",")


LARGE_MESSAGE_BYTES = 256 * 1024
"""Larger messages are parsed off the event loop (:meth:`Dispatcher.parse_off_loop`)."""
_C_ENCODE = (
    # What JSONEncoder.encode builds anew on every call (the C encoder, with its options),
    # built once. No circular-reference markers: a cyclic result ends in RecursionError.
    json.encoder.c_make_encoder(  # type: ignore[attr-defined]
        None,
        _ENCODER.default,
        json.encoder.encode_basestring_ascii,
        None,
        ":",
        ",",
        False,
        False,
        False,
    )
    if getattr(json.encoder, "c_make_encoder", None) is not None
    else None
)


def decode(data: bytes | str) -> Any:
    """A JSON document (``NaN``/``Infinity`` refused); raises ``ValueError``/``RecursionError``.

    A number too large for a float (``1e999``) still decodes, to ``inf``: the envelope checks
    refuse it where it matters (ids, float params) and the encoder never sends one back.
    """
    return _decode(_DECODER, data if isinstance(data, str) else _text(data))


def _decode(decoder: json.JSONDecoder, text: str) -> Any:
    """``decoder.decode(text)``, minus two regex matches when there is no whitespace around."""
    try:
        value, end = decoder.scan_once(text, 0)  # type: ignore[attr-defined]
    except StopIteration:
        end = -1  # leading whitespace, or not JSON: the full decoder says which
    if end != len(text):  # (or trailing whitespace, or extra data)
        return decoder.decode(text)
    return value


def _encode(message: Any) -> str:
    if _C_ENCODE is None:
        return _ENCODER.encode(message)
    return "".join(_C_ENCODE(message, 0))


def _encode_id(request_id: Any) -> str:
    """An id already checked valid (int, str, finite float or None)."""
    return str(request_id) if type(request_id) is int else _encode(request_id)


def encode_error(request_id: Any, err: RpcError) -> bytes:
    """An error answer (``request_id`` None when the request's could not be read)."""
    return _encode(_error_response(_valid_id(request_id), err)).encode()


class EncodedParams(str):
    """Params already encoded as a JSON object or array, sent as they are: for params a client
    repeats on every call (a session's token), encoded once instead of per call."""

    __slots__ = ()

    @classmethod
    def of(cls, params: dict[str, Any] | list[Any]) -> EncodedParams:
        return cls(_encode(params))


def request_text(
    method: str,
    params: dict[str, Any] | list[Any] | EncodedParams | None,
    request_id: int | None,
) -> str:
    """A request (or a notification when ``request_id`` is None)."""
    # The envelope by hand, as for answers: only the method's name and params are encoded.
    text = '{"jsonrpc":"2.0","method":' + encode_basestring_ascii(method)
    if type(params) is EncodedParams:
        text += ',"params":' + params
    elif params is not None:
        text += ',"params":' + _encode(params)
    return text + ("}" if request_id is None else f',"id":{request_id}}}')


def encode_request(
    method: str,
    params: dict[str, Any] | list[Any] | EncodedParams | None,
    request_id: int | None,
) -> bytes:
    """:func:`request_text`, encoded (for an HTTP body)."""
    return request_text(method, params, request_id).encode()


class BadAnswer(ValueError):
    """An answer that is not a JSON-RPC 2.0 response; ``request_id`` when one could be read."""

    def __init__(self, reason: str, request_id: int | None = None) -> None:
        super().__init__(reason)
        self.request_id = request_id


@dataclass(slots=True)
class Answer:
    """One response to a request of ours: its ``result``, or the ``error`` it carries."""

    request_id: int
    result: Any = None
    error: RpcError | None = None

    def value(self) -> Any:
        """The result; raises the :class:`RpcError` of an error answer."""
        if self.error is not None:
            raise self.error
        return self.result


def read_answer(item: Any) -> Answer:
    """Check one decoded response object (our requests carry int ids); raises
    :class:`BadAnswer` for anything else: clients count and drop it, never die on it."""
    if type(item) is not dict:
        raise BadAnswer(f"not an object: {type(item).__name__}")
    request_id = item.get("id")
    if type(request_id) is not int:
        raise BadAnswer(f"id {request_id!r:.40} is not one of ours")
    if "error" in item:
        error = item["error"]
        if type(error) is not dict:
            raise BadAnswer("error is not an object", request_id)
        code, message = error.get("code"), error.get("message", "")
        if type(code) is not int or type(message) is not str:
            raise BadAnswer(f"error code {code!r:.40} or message is malformed", request_id)
        return Answer(request_id, error=RpcError(code, message, error.get("data")))
    if "result" not in item:
        raise BadAnswer("neither result nor error", request_id)
    return Answer(request_id, item["result"])


def decode_answers(data: bytes | str) -> list[Any]:
    """The response objects in a received message (one, or a batch's); raises ``ValueError``
    (or ``RecursionError``) when it is not JSON, or when it holds a number no float can
    represent (``1e999``), which no conforming peer sends."""
    answer = decode_answer_message(data)
    return answer if isinstance(answer, list) else [answer]


def decode_answer_message(data: bytes | str) -> Any:
    """A received message decoded as it is (a response object, or a batch's list); raises as
    :func:`decode_answers`.

    Answers are read with orjson: every station reads one per heartbeat, and the standard
    library's decoder, with its Python-level wrapper, costs several times as much per answer.
    What an answer may hold decodes alike, with two differences that cannot matter for answers
    to our own requests: orjson reads an integer beyond 64 bits as a float (our ids are
    counters), and it refuses a few documents the standard library reads (a lone surrogate
    escape, UTF-16 text). Those take the standard library's path, which then decides.
    Requests, which anyone may send, keep the standard library's reading (:func:`decode`):
    an id must be echoed exactly.
    """
    try:
        return orjson.loads(data)
    except orjson.JSONDecodeError:
        return _decode(_ANSWER_DECODER, data if isinstance(data, str) else _text(data))


def _text(data: bytes) -> str:
    return data.decode(json.detect_encoding(data), "surrogatepass")


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"{text:.40} does not fit a float")
    return value


_ANSWER_DECODER = json.JSONDecoder(parse_constant=_refuse_constant, parse_float=_finite_float)
