"""Property tests of the whole JSON-RPC envelope path through real sockets: arbitrary requests
to a real in-process platform over HTTP (``/rpc``) and WebSocket (``/rpc/ws``), and arbitrary
answers to the clients. Every request gets one valid JSON-RPC answer (none for a
notification), the answer is JSON proper (no NaN/Infinity), the socket and the session stay
open, and a client never dies of what it is sent."""

from __future__ import annotations

import asyncio
import json
from collections.abc import AsyncIterator
from typing import Any

import aiohttp
import pytest
from aiohttp import web
from conftest import quiet_platform_config
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from brasidas.actor import Supervisor
from brasidas.bus import Bus
from brasidas.codecs.jsonrpc import RpcError
from brasidas.config import StationConfig, load_config
from brasidas.rpc import RpcClient, serve_app
from platformd.app import PlatformDaemon
from stationd.api_client import CliError, api_call_async

FUZZ = settings(
    max_examples=40,
    deadline=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)
"""Bounded: each example is a few round trips on loopback; the whole file runs in seconds."""

SESSION = "\x00session"
"""Stands for the example's live session token in generated params."""

SAFE_WITH_SESSION = [
    "heartbeat",
    "get_platform_parameters",
    "get_telemetry_report",
    "get_velocity_connection_info",
    "get_nav_camera_parameters",
    "list_streams",
    "set_manual_override",
    "set_lights",
    "issue_system_command",
    "pause_stream",
    "stop_stream",
    "stop_telemetry",
]
"""Methods run past the authorizer with random params. Not: ``disconnect`` (would end the
session under test), ``start_stream``/``request_telemetry`` (a random host could send off
loopback)."""

json_scalars = (
    st.none()
    | st.booleans()
    | st.integers()
    | st.integers(min_value=10**30, max_value=10**60)
    | st.floats()  # NaN and ±inf included: sent as NaN / ±1e999
    | st.text(max_size=8)
)
json_values = st.recursive(
    json_scalars,
    lambda children: (
        st.lists(children, max_size=3) | st.dictionaries(st.text(max_size=6), children, max_size=3)
    ),
    max_leaves=8,
)
ids = json_values | st.integers() | st.text(max_size=6)
METHODS = [*SAFE_WITH_SESSION, "challenge", "connect", "nope"]
params = (
    json_values
    | st.lists(json_scalars, max_size=3)
    | st.dictionaries(st.sampled_from(["session", "engaged", "which", "on", "group"]), json_values)
)
GOOD_PARAMS: dict[str, dict[str, st.SearchStrategy[Any]]] = {
    "connect": {"station_id": st.text(min_size=1, max_size=8)},
    "set_manual_override": {"engaged": st.booleans()},
    "set_lights": {"which": st.sampled_from(["main", "pos"]), "on": st.booleans()},
    "issue_system_command": {
        "group": st.integers(0, 12),
        "command": st.integers(0, 12),
        "payload": st.text(max_size=6),
    },
    "pause_stream": {"name": st.sampled_from(["navcam", "audio_out", "x"])},
    "stop_stream": {"name": st.sampled_from(["navcam", "audio_out", "x"])},
}
"""By-name params each method takes, right in type; the session is added for the others."""


@st.composite
def envelopes(draw: st.DrawFn) -> Any:
    """A request-shaped object: mostly well-formed, each field sometimes missing or wrong."""

    def often() -> bool:
        return draw(st.integers(0, 19)) not in (0, 19)  # Hypothesis favours the bounds

    message: dict[str, Any] = {}
    if often():
        message["jsonrpc"] = "2.0" if often() else draw(json_scalars)
    method = draw(st.sampled_from(METHODS))
    if often():
        message["method"] = method if often() else draw(json_values)
    if often():
        good = draw(st.fixed_dictionaries(GOOD_PARAMS.get(method, {})))
        if method in SAFE_WITH_SESSION and often():
            good["session"] = SESSION
        if not often():  # one value of the wrong type, or one too many
            good[draw(st.sampled_from([*good, "extra"]))] = draw(json_values)
        message["params"] = good if often() else draw(params)
    if often():
        message["id"] = draw(st.integers() | st.text(max_size=6)) if often() else draw(ids)
    if not often():
        message[draw(st.text(max_size=5))] = draw(json_values)
    return message


@st.composite
def requests(draw: st.DrawFn) -> Any:
    """Mostly requests a buggy station could send; sometimes a batch, any JSON, any bytes."""
    kind = draw(st.integers(0, 19))
    if kind < 14:
        return draw(envelopes())
    if kind < 17:
        return draw(st.lists(envelopes() | json_scalars, max_size=4))
    if kind < 19:
        return draw(json_values)
    return ("raw", draw(st.binary(max_size=40)))


def render(request: Any, token: str) -> bytes:
    """Bytes on the wire; non-finite floats as the literals NaN and ±1e999."""
    if isinstance(request, tuple):
        return bytes(request[1])
    text = json.dumps(request).replace(json.dumps(SESSION), json.dumps(token))
    return text.replace("-Infinity", "-1e999").replace("Infinity", "1e999").encode()


OPEN_METHODS = ("challenge", "connect")
"""What a connection without a session may batch."""


def expected_answers(raw: bytes, *, stranger: bool = False) -> tuple[Any, int | None]:
    """What the server reads in ``raw`` and how many answers it owes: None for no message,
    else the items (1 for a single one). A ``stranger``'s batch of anything but calls that
    need no session is answered with one error."""
    try:
        request = json.loads(raw, parse_constant=_not_json)
    except ValueError:
        return ("raw", raw), 1  # parse error
    if not isinstance(request, dict | list):
        return request, 1  # -32600
    if isinstance(request, list):
        if not request:
            return request, 1
        # A stranger's batch is refused whole for a call of a method needing a session; what
        # is no request at all is answered -32600 each (JSON-RPC's ``[1,2,3]`` example).
        if stranger and any(
            isinstance(item, dict)
            and isinstance(item.get("method"), str)
            and item["method"] not in OPEN_METHODS
            for item in request
        ):
            return {"refused batch": request}, 1
        return request, sum(1 for item in request if _answered(item)) or None
    return request, 1 if _answered(request) else None


def _not_json(name: str) -> Any:
    raise ValueError(name)


def _answered(item: Any) -> bool:
    """Everything is answered but a well-formed notification."""
    if not isinstance(item, dict) or item.get("jsonrpc") != "2.0" or "id" in item:
        return True
    return not isinstance(item.get("method"), str) or not isinstance(
        item.get("params", {}), dict | list
    )


def strict_json(data: bytes | str) -> Any:
    def refuse(name: str) -> Any:
        raise AssertionError(f"{name} in an answer: {data!r:.200}")

    return json.loads(data, parse_constant=refuse)


def check_answer(answer: Any, count: int | None, request: Any) -> None:
    """One valid JSON-RPC answer (or a batch of ``count``) to ``request``."""
    items = answer if isinstance(answer, list) else [answer]
    if isinstance(request, list) and request:
        assert isinstance(answer, list), (request, answer)
        assert len(items) == count, (request, answer)
    else:
        assert isinstance(answer, dict), (request, answer)
    for item in items:
        assert item["jsonrpc"] == "2.0", item
        assert ("result" in item) != ("error" in item), item
        assert isinstance(item["id"], str | int | float | None), item
        assert not isinstance(item["id"], bool), item
        if "error" in item:
            assert type(item["error"]["code"]) is int, item
            assert isinstance(item["error"]["message"], str), item
    if isinstance(request, dict) and isinstance(request.get("id"), str | int):
        if not isinstance(request.get("id"), bool):
            assert answer["id"] in (request["id"], None), (request, answer)


@pytest.fixture
async def platform(platform_factory: Any) -> PlatformDaemon:
    daemon: PlatformDaemon = await platform_factory(quiet_platform_config(), None)
    return daemon


async def _connect(ws: aiohttp.ClientWebSocketResponse) -> str:
    await ws.send_str('{"jsonrpc":"2.0","id":"open","method":"connect","params":["fuzz"]}')
    return str(strict_json((await asyncio.wait_for(ws.receive(), 10)).data)["result"]["session"])


@FUZZ
@given(st.lists(requests(), min_size=1, max_size=6))
async def test_any_request_over_the_websocket_is_answered_on_an_open_socket(
    platform: PlatformDaemon, batch: list[Any]
) -> None:
    async with (
        aiohttp.ClientSession() as session,
        session.ws_connect(platform.ctx.signaling_url + "/rpc/ws") as ws,
    ):
        token = await _connect(ws)
        for number, request in enumerate(batch):
            raw = render(request, token)
            request, count = expected_answers(raw)
            probe = f"probe-{number}"
            await ws.send_bytes(raw)
            await ws.send_str(f'{{"jsonrpc":"2.0","id":"{probe}","method":"challenge"}}')
            answers: list[Any] = []
            probed = False
            while not probed or len(answers) < (count is not None):
                message = await asyncio.wait_for(ws.receive(), 10)
                assert message.type == aiohttp.WSMsgType.TEXT, (request, message)
                answer = strict_json(message.data)
                if isinstance(answer, dict) and answer.get("id") == probe:
                    probed = True
                else:
                    answers.append(answer)
            assert len(answers) == (count is not None), (request, answers)
            if answers:
                check_answer(answers[0], count, request)
        assert not ws.closed
        assert token in platform.ctx.sessions.sessions


@FUZZ
@given(requests())
async def test_any_request_over_http_is_answered(platform: PlatformDaemon, request: Any) -> None:
    raw = render(request, "")
    async with (
        aiohttp.ClientSession() as session,
        session.post(platform.ctx.signaling_url + "/rpc", data=raw) as response,
    ):
        body = await response.read()
    request, count = expected_answers(raw, stranger=True)
    if count is None:
        assert response.status == 204, (request, body)
        assert not body, (request, body)
        return
    assert response.status in (200, 401), (request, response.status)
    check_answer(strict_json(body), count, request)


# ---------------------------------------------------------------------------- client side


class Scripted:
    """Answers every request with the answers an example drew, then the right one."""

    def __init__(self) -> None:
        self.answers: list[bytes] = []
        self.url = ""

    def script(self, request: bytes) -> list[bytes]:
        request_id = json.loads(request)["id"]
        right = json.dumps({"jsonrpc": "2.0", "id": request_id, "result": "right"})
        return [a.replace(b'"ID"', str(request_id).encode()) for a in self.answers] + [
            right.encode()
        ]

    async def websocket(self, request: web.Request) -> web.StreamResponse:
        ws = web.WebSocketResponse()
        await ws.prepare(request)
        async for message in ws:
            for raw in self.script(message.data.encode()):
                await ws.send_bytes(raw) if raw[:1] == b"\xff" else await ws.send_str(
                    raw.decode("utf-8", "replace")
                )
        return ws

    async def post(self, request: web.Request) -> web.Response:
        answers = self.script(await request.read())
        return web.Response(body=answers[0], content_type="application/json")


@pytest.fixture
async def scripted() -> AsyncIterator[Scripted]:
    server = Scripted()
    app = web.Application()
    app.router.add_get("/ws", server.websocket)
    app.router.add_post("/api/rpc", server.post)
    supervisor = Supervisor()
    port = await serve_app(app, "127.0.0.1", 0, supervisor=supervisor, bus=Bus(), name="fuzz")
    server.url = f"http://127.0.0.1:{port}"
    yield server
    await supervisor.stop(2.0)


answer_ids = st.just("ID") | ids
answer_bodies = st.fixed_dictionaries(
    {"jsonrpc": st.just("2.0") | json_scalars, "id": answer_ids},
    optional={
        "result": json_values,
        "error": json_values
        | st.fixed_dictionaries(
            {"code": json_scalars | st.integers(), "message": json_scalars},
            optional={"data": json_values},
        ),
    },
)
answers = st.lists(
    (answer_bodies | st.lists(answer_bodies | json_values, max_size=3) | json_values).map(
        lambda value: render(value, "").replace(b'"\\"ID\\""', b'"ID"')
    )
    | st.binary(max_size=30),
    max_size=4,
)


@FUZZ
@given(answers)
async def test_the_client_survives_any_answer(scripted: Scripted, drawn: list[bytes]) -> None:
    scripted.answers = drawn
    async with RpcClient(scripted.url + "/ws", timeout=10) as client:
        for _ in range(2):
            try:
                await client.call("anything")
            except RpcError:
                pass  # an error answer, or a malformed one, to this very call: fine
            assert not client.closed.is_set()
        scripted.answers = []
        assert await client.call("anything") == "right"


@FUZZ
@given(answers)
async def test_the_local_api_client_survives_any_answer(
    scripted: Scripted, drawn: list[bytes]
) -> None:
    scripted.answers = drawn
    port = scripted.url.rsplit(":", 1)[1]
    config = load_config(
        StationConfig, None, ["station.api_host=127.0.0.1", f"station.api_port={port}"]
    )
    try:
        await api_call_async(config, "anything")
    except (RpcError, CliError):
        pass  # anything else (TypeError, KeyError, ValueError) fails the test
