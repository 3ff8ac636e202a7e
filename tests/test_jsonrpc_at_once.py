"""The dispatcher's inline answer (the WebSocket's path for methods that answer at once, with
its own fast path for the usual request) says exactly what the general path says, and
counts alike."""

from __future__ import annotations

import math
from typing import Any

import pytest

from brasidas.codecs.jsonrpc import CallContext, Dispatcher, RpcError, Unauthorized

MESSAGES = [
    '{"jsonrpc":"2.0","method":"echo","params":{"session":"good","text":"hi"},"id":1}',
    '{"jsonrpc":"2.0","method":"echo","params":{"session":"bad","text":"hi"},"id":2}',
    '{"jsonrpc":"2.0","method":"echo","params":{"text":"hi"},"id":3}',
    '{"jsonrpc":"2.0","method":"echo","params":{"session":"good","text":5},"id":4}',
    '{"jsonrpc":"2.0","method":"echo","params":{"session":"good","other":1},"id":5}',
    '{"jsonrpc":"2.0","method":"echo","params":{"session":"good"},"id":6}',
    '{"jsonrpc":"2.0","method":"echo","params":["hi"],"id":7}',
    '{"jsonrpc":"2.0","method":"echo","params":{"session":"good","text":"hi"}}',
    '{"jsonrpc":"2.0","method":"echo","params":{"session":"good","text":"hi"},"id":"s"}',
    '{"jsonrpc":"2.0","method":"echo","params":{"session":"good","text":"hi"},"id":1.5}',
    '{"jsonrpc":"2.0","method":"echo","id":8}',
    '{"jsonrpc":"1.0","method":"echo","params":{"session":"good","text":"hi"},"id":9}',
    '{"jsonrpc":"2.0","method":"nothing","params":{},"id":10}',
    '{"jsonrpc":"2.0","method":"refuse","params":{},"id":11}',
    '{"jsonrpc":"2.0","method":"crash","params":{},"id":12}',
    '{"jsonrpc":"2.0","method":"nan","params":{},"id":13}',
    '{"jsonrpc":"2.0","method":"open","params":{},"id":14}',
    '{"jsonrpc":"2.0","method":"echo","params":{"session":"good","text":"hi"},"id":true}',
    '{"jsonrpc":"2.0","method":7,"params":{},"id":15}',
    '{"jsonrpc":"2.0","method":"echo","params":"x","id":16}',
    "not json",
]


def authorize(call: CallContext, params: dict[str, Any]) -> None:
    if params.pop("session", None) != "good":
        raise Unauthorized("unauthorized: no valid session")
    call.session = "good"


def crash(call: CallContext) -> None:
    raise ValueError("a bug")


def refuse(call: CallContext) -> None:
    raise RpcError(-32010, "refused")


def dispatcher() -> Dispatcher:
    rpc = Dispatcher(authorize)
    rpc.add("echo", lambda call, text: {"text": text, "session": call.session})
    rpc.add("open", lambda call: "opened", session_required=False)
    rpc.add("refuse", refuse, session_required=False)
    rpc.add("crash", crash, session_required=False)
    rpc.add("nan", lambda call: math.nan, session_required=False)
    return rpc


@pytest.mark.parametrize("stranger", [False, True])
async def test_the_inline_answer_is_the_general_answer(stranger: bool) -> None:
    inline, general = dispatcher(), dispatcher()
    sessions_opened: list[str] = []
    for text in MESSAGES:
        inline_call = CallContext(peer_host="127.0.0.1", transport="ws", stranger=stranger)
        inline_call.on_session = lambda: sessions_opened.append("inline")
        general_call = CallContext(peer_host="127.0.0.1", transport="ws", stranger=stranger)
        general_call.on_session = lambda: sessions_opened.append("general")
        incoming = inline.parse(text)
        assert inline.answers_at_once(incoming), text
        answer = inline.answer_at_once(incoming, inline_call)
        assert answer == await general.answer(general.parse(text), general_call), text
        assert inline_call.stranger == general_call.stranger, text
    assert inline.counters == general.counters
    assert inline.counters["calls"] == 16
    assert inline.counters["unauthorized"] == 4  # a wrong, two missing and a by-position session
    assert sessions_opened.count("inline") == sessions_opened.count("general")
    assert (sessions_opened.count("inline") > 0) == stranger  # a stranger's first good call
