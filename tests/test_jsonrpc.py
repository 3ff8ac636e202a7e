"""JSON-RPC 2.0 conformance of the sans-IO dispatcher."""

from __future__ import annotations

import json
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brasidas.codecs.jsonrpc import (
    CallContext,
    Dispatcher,
    EncodedParams,
    RpcError,
    Unauthorized,
    decode_answers,
    request_text,
)


async def _echo(call: CallContext, value: int, label: str = "x") -> dict[str, Any]:
    return {"value": value, "label": label}


def _scale(call: CallContext, factor: float) -> float:
    return factor * 2


def _nan(call: CallContext) -> float:
    return float("nan")  # a sensor that failed


async def _boom(call: CallContext) -> None:
    raise ZeroDivisionError("secret detail")


async def _whoami(call: CallContext) -> str:
    return str(call.session)


def _authorize(call: CallContext, params: dict[str, Any]) -> None:
    if params.pop("session", None) != "good":
        raise Unauthorized()
    call.session = "alice"


@pytest.fixture
def dispatcher() -> Dispatcher:
    d = Dispatcher(authorizer=_authorize)
    d.add("echo", _echo, session_required=False)
    d.add("boom", _boom, session_required=False)
    d.add("whoami", _whoami)
    d.add("scale", _scale, session_required=False)
    d.add("nan", _nan, session_required=False)
    return d


async def ask(d: Dispatcher, payload: Any) -> Any:
    """The answer through the doors a transport uses (``answers_at_once``, then
    ``answer_at_once`` or ``answer``), checked to be JSON proper (no NaN or Infinity)."""
    raw = payload if isinstance(payload, bytes) else json.dumps(payload).encode()
    incoming = d.parse(raw)
    if d.answers_at_once(incoming):  # must not raise, whatever the message
        answer = d.answer_at_once(incoming, CallContext())
    else:
        answer = await d.answer(incoming, CallContext())
    return None if answer is None else json.loads(answer, parse_constant=_not_json)


def _not_json(name: str) -> Any:
    raise AssertionError(f"{name} is not JSON")


async def test_named_and_positional_params(dispatcher: Dispatcher) -> None:
    named = await ask(
        dispatcher, {"jsonrpc": "2.0", "id": 1, "method": "echo", "params": {"value": 3}}
    )
    assert named == {"jsonrpc": "2.0", "id": 1, "result": {"value": 3, "label": "x"}}
    positional = await ask(
        dispatcher, {"jsonrpc": "2.0", "id": "a", "method": "echo", "params": [4, "y"]}
    )
    assert positional["result"] == {"value": 4, "label": "y"}


@pytest.mark.parametrize(
    ("payload", "code"),
    [
        (b"{not json", -32700),
        ({"jsonrpc": "1.0", "id": 1, "method": "echo"}, -32600),
        ({"jsonrpc": "2.0", "id": 1, "method": 5}, -32600),
        ({"jsonrpc": "2.0", "id": {"x": 1}, "method": "echo"}, -32600),
        ({"jsonrpc": "2.0", "id": 1, "method": "echo", "params": "nope"}, -32600),
        ({"jsonrpc": "2.0", "id": 1, "method": "nope"}, -32601),
        ({"jsonrpc": "2.0", "id": 1, "method": "echo", "params": {}}, -32602),
        ({"jsonrpc": "2.0", "id": 1, "method": "echo", "params": {"value": 1, "bogus": 2}}, -32602),
        ({"jsonrpc": "2.0", "id": 1, "method": "echo", "params": {"value": "1"}}, -32602),
        ({"jsonrpc": "2.0", "id": 1, "method": "echo", "params": {"value": True}}, -32602),
        ({"jsonrpc": "2.0", "id": 1, "method": "echo", "params": [1, 2, 3]}, -32602),
        ({"jsonrpc": "2.0", "id": 1, "method": "boom"}, -32603),
        ({"jsonrpc": "2.0", "id": 1, "method": "whoami"}, -32001),
        ({"jsonrpc": "2.0", "id": 1, "method": "whoami", "params": {"session": "bad"}}, -32001),
        ([], -32600),
        ({"jsonrpc": "2.0", "id": 1, "method": [1]}, -32600),
        ({"jsonrpc": "2.0", "id": 1, "method": {"echo": 1}}, -32600),
        (b'{"jsonrpc":"2.0","id":1e999,"method":"echo","params":[1]}', -32600),
        (b'{"jsonrpc":"2.0","id":-1e999,"method":"echo","params":[1]}', -32600),
        (b'{"jsonrpc":"2.0","id":NaN,"method":"echo","params":[1]}', -32700),
        (b'{"jsonrpc":"2.0","id":1,"method":"echo","params":[Infinity]}', -32700),
        (b'{"jsonrpc":"2.0","id":1,"method":"scale","params":[1e999]}', -32602),
        (b'{"jsonrpc":"2.0","id":1,"method":"nan"}', -32603),
        (b'{"jsonrpc":"2.0","id":1' + b"0" * 5000 + b',"method":"nan"}', -32700),  # > int digits
        (b'{"jsonrpc":"2.0","id":1,"method":"scale","params":[1' + b"0" * 5000 + b"]}", -32700),
    ],
)
async def test_standard_errors(dispatcher: Dispatcher, payload: Any, code: int) -> None:
    answer = await ask(dispatcher, payload)
    assert answer["error"]["code"] == code
    if code in (-32600, -32700):
        assert answer["id"] in (None, 1)
    assert "secret detail" not in answer["error"]["message"]


async def test_session_method_with_valid_session(dispatcher: Dispatcher) -> None:
    answer = await ask(
        dispatcher, {"jsonrpc": "2.0", "id": 1, "method": "whoami", "params": {"session": "good"}}
    )
    assert answer["result"] == "alice"
    assert dispatcher.counters["unauthorized"] == 0


async def test_notifications_get_no_answer_even_on_error(dispatcher: Dispatcher) -> None:
    assert (
        await ask(dispatcher, {"jsonrpc": "2.0", "method": "echo", "params": {"value": 1}}) is None
    )
    assert await ask(dispatcher, {"jsonrpc": "2.0", "method": "boom"}) is None
    assert await ask(dispatcher, [{"jsonrpc": "2.0", "method": "echo", "params": [1]}]) is None


async def test_batch_answers_each_call_in_order(dispatcher: Dispatcher) -> None:
    batch = [
        {"jsonrpc": "2.0", "id": 1, "method": "echo", "params": [1]},
        {"jsonrpc": "2.0", "method": "echo", "params": [2]},
        {"jsonrpc": "2.0", "id": 3, "method": "nope"},
        7,
    ]
    answer = await ask(dispatcher, batch)
    assert [item.get("id") for item in answer] == [1, 3, None]
    assert answer[0]["result"]["value"] == 1
    assert answer[1]["error"]["code"] == -32601
    assert answer[2]["error"]["code"] == -32600


async def test_counters_count_bad_input(dispatcher: Dispatcher) -> None:
    await ask(dispatcher, b"\xff\xfe")
    await ask(dispatcher, {"jsonrpc": "2.0", "id": 1, "method": "nope"})
    await ask(dispatcher, {"jsonrpc": "2.0", "id": 1, "method": "whoami"})
    assert dispatcher.counters["parse_errors"] == 1
    assert dispatcher.counters["unknown_methods"] == 1
    assert dispatcher.counters["unauthorized"] == 1


async def test_nesting_deeper_than_the_parser_is_a_parse_error(dispatcher: Dispatcher) -> None:
    answer = await ask(dispatcher, b"[" * 100_000)
    assert answer["error"]["code"] == -32700
    assert answer["id"] is None
    assert dispatcher.counters["parse_errors"] == 1


async def test_rpc_error_from_method_is_passed_through() -> None:
    async def refuse(call: CallContext) -> None:
        raise RpcError(-32002, "no camera", {"hint": "x"})

    d = Dispatcher()
    d.add("refuse", refuse, session_required=False)
    answer = await ask(d, {"jsonrpc": "2.0", "id": 9, "method": "refuse"})
    assert answer["error"] == {"code": -32002, "message": "no camera", "data": {"hint": "x"}}


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=200) | st.text(max_size=200).map(str.encode))
async def test_arbitrary_bytes_never_raise(data: bytes) -> None:
    d = Dispatcher()
    d.add("echo", _echo, session_required=False)
    answer = await d.handle_bytes(data, CallContext())
    if answer is not None:
        decoded = json.loads(answer)
        items = decoded if isinstance(decoded, list) else [decoded]
        assert all(item["jsonrpc"] == "2.0" for item in items)


@settings(max_examples=200, deadline=None)
@given(
    st.recursive(
        st.none()
        | st.booleans()
        | st.integers()
        | st.floats(allow_nan=False)
        | st.text(max_size=10),
        lambda children: (
            st.lists(children, max_size=4)
            | st.dictionaries(st.text(max_size=8), children, max_size=4)
        ),
        max_leaves=12,
    )
)
async def test_arbitrary_json_never_raises(value: Any) -> None:
    d = Dispatcher()
    d.add("echo", _echo, session_required=False)
    await d.handle_bytes(json.dumps(value).encode(), CallContext())


async def test_a_large_integer_id_is_echoed_exactly(dispatcher: Dispatcher) -> None:
    big = 10**300
    answer = await ask(dispatcher, {"jsonrpc": "2.0", "id": big, "method": "scale", "params": [2]})
    assert answer == {"jsonrpc": "2.0", "id": big, "result": 4}


# The client's side: answers are read with orjson, which must read them as the standard library
# does (exactly, for what answers to our requests hold), and requests with params encoded once.

_answer_values = st.recursive(
    st.none()
    | st.booleans()
    | st.integers(min_value=-(2**63), max_value=2**63 - 1)
    | st.floats(allow_nan=False, allow_infinity=False)
    | st.text(),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4)
    ),
    max_leaves=12,
)


@given(_answer_values, st.booleans())
def test_answers_decode_as_the_standard_library_reads_them(value: Any, ascii_only: bool) -> None:
    text = json.dumps({"jsonrpc": "2.0", "id": 7, "result": value}, ensure_ascii=ascii_only)
    for data in (text, text.encode()):
        assert decode_answers(data) == [json.loads(text)]


@pytest.mark.parametrize(
    ("data", "expected"),
    [
        # JSON orjson refuses: read by the standard library instead, as before.
        ('{"id":1,"result":"\\ud800"}', {"id": 1, "result": "\ud800"}),
        ('{"id":1,"result":1}'.encode("utf-16"), {"id": 1, "result": 1}),
    ],
)
def test_answers_orjson_refuses_are_read_by_the_standard_library(
    data: str | bytes, expected: Any
) -> None:
    assert decode_answers(data) == [expected]


@pytest.mark.parametrize(
    "data", ['{"id":1,"result":NaN}', '{"id":1,"result":1e999}', "Infinity", "not json", ""]
)
def test_answers_that_are_not_json_are_refused(data: str) -> None:
    with pytest.raises(ValueError):
        decode_answers(data)


def test_params_encoded_once_make_the_same_request() -> None:
    params = {"session": "tok\u00e9n", "n": [1, 2.5, None]}
    assert request_text("go", EncodedParams.of(params), 4) == request_text("go", params, 4)
    assert json.loads(request_text("go", EncodedParams.of(params), None)) == {
        "jsonrpc": "2.0",
        "method": "go",
        "params": params,
    }


async def test_the_specifications_batch_of_numbers_gets_an_error_each_before_a_session(
    dispatcher: Dispatcher,
) -> None:
    """JSON-RPC 2.0's own example: ``[1,2,3]`` is answered with three -32600 errors, also
    from a stranger (bounded by the batch cap); a session method in its batch is refused whole."""
    incoming = dispatcher.parse(b"[1,2,3]")
    answer = await dispatcher.answer(incoming, CallContext(stranger=True))
    assert answer is not None
    errors = json.loads(answer)
    assert [e["error"]["code"] for e in errors] == [-32600] * 3
    assert all(e["id"] is None for e in errors)
    mixed = json.dumps([1, {"jsonrpc": "2.0", "id": 1, "method": "whoami"}]).encode()
    refused = json.loads(
        await dispatcher.answer(dispatcher.parse(mixed), CallContext(stranger=True)) or "null"
    )
    assert isinstance(refused, dict)
    assert refused["error"]["code"] == -32600
