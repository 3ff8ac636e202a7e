"""The client of the running station daemon's local API (JSON-RPC over HTTP POST), used by the
operator's commands. Answers are read by the one JSON-RPC client code path
(:func:`brasidas.codecs.jsonrpc.read_answer`), as the platform client reads its own."""

from __future__ import annotations

from typing import Any

import aiohttp

from brasidas.codecs.jsonrpc import (
    INTERNAL_ERROR,
    BadAnswer,
    RpcError,
    decode_answers,
    encode_request,
    read_answer,
)
from brasidas.config import StationConfig
from brasidas.limits import STATION_API_MAX_BYTES


class CliError(Exception):
    """Printed as one line; the command exits 1."""


async def api_call_async(config: StationConfig, method: str, **params: Any) -> Any:
    """Call the running station daemon's local API; raises CliError or RpcError."""
    station = config.station
    url = f"http://{station.api_host}:{station.api_port}/api/rpc"
    request = encode_request(method, params, 1)
    if len(request) > STATION_API_MAX_BYTES:
        raise CliError(
            f"{method}: the request is {len(request)} bytes, over the limit of "
            f"{STATION_API_MAX_BYTES} bytes for one call (a map or a route; docs/operator-guide.md: Limits)"
        )
    timeout = aiohttp.ClientTimeout(total=station.connect_timeout * 2 + 2)
    try:
        async with (
            aiohttp.ClientSession(timeout=timeout) as session,
            session.post(url, data=request) as response,
        ):
            body = await response.read()
    except aiohttp.ClientConnectionError:
        raise CliError(
            f"the station daemon is not running at {url} (start it with 'brasidas-station serve')"
        ) from None
    except TimeoutError:
        raise CliError(f"no answer from the station daemon within {timeout.total:.0f} s") from None
    if response.status == 413:
        raise CliError(f"{method}: the station daemon refused the request: {_reason(body)}")
    try:
        items = decode_answers(body)
        if len(items) != 1:
            raise BadAnswer(f"{len(items)} answers to one call")
        return read_answer(items[0]).value()
    except (ValueError, RecursionError) as err:  # BadAnswer is a ValueError
        raise RpcError(
            INTERNAL_ERROR,
            f"the station daemon answered {response.status} with no valid JSON-RPC answer ({err})",
        ) from None


def _reason(body: bytes) -> str:
    """The message of an error answer without an id (a refusal before the request was read)."""
    try:
        error = decode_answers(body)[0].get("error", {})
        return str(error.get("message", body[:200].decode(errors="replace")))
    except (ValueError, RecursionError, IndexError, AttributeError):
        return body[:200].decode(errors="replace")
