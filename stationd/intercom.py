"""``brasidas-station audio ID [--talk]``: two-way audio with a platform (R-11.3).

The station daemon plays the platform's microphone (its ``audio_out`` stream) on this
station's speaker and, with ``--talk``, sends this station's microphone (or ``--test-tone``)
to the platform's speaker (``audio_in``). The command prints what arrives once a second and,
when it ends (Ctrl-C, ``--seconds``), stops both streams.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import sys
from typing import Any

from brasidas.actor import stop_on_signals
from brasidas.codecs.jsonrpc import RpcError
from brasidas.config import StationConfig
from stationd.api_client import CliError, api_call_async


def run_audio(args: argparse.Namespace, config: StationConfig) -> int:
    return asyncio.run(_audio(args, config))


async def _audio(args: argparse.Namespace, config: StationConfig) -> int:
    await api_call_async(config, "connect", platform_id=args.id, url=args.url or "")
    stop = stop_on_signals()
    loop = asyncio.get_running_loop()
    listening = talking = False
    try:
        heard = await api_call_async(
            config, "receive", platform_id=args.id, stream="audio_out", sink=args.sink
        )
        listening = True
        _say(args, f"listening: {args.id}'s microphone on UDP {heard.get('port')}", heard)
        if args.talk:
            sent = await api_call_async(
                config, "talk", platform_id=args.id, on=True, test_tone=args.test_tone
            )
            talking = True
            source = "a test tone" if args.test_tone else "this station's microphone"
            _say(args, f"talking: {source} to {sent.get('host')}:{sent.get('port')}", sent)
        deadline = loop.time() + args.seconds if args.seconds else None
        heard_anything = False
        while not stop.is_set():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), 1.0)
            receiver = await _receiver(config, args.id)
            if receiver is None:
                raise CliError("the station stopped receiving (platform gone?)")
            if receiver.get("state") == "failed":
                raise CliError(f"receiver failed: {receiver.get('reason')}")
            heard_anything = heard_anything or int(receiver.get("buffers", 0)) > 0
            _say(
                args,
                f"buffers {receiver.get('buffers')}  peak {receiver.get('peak')}",
                {"buffers": receiver.get("buffers"), "peak": receiver.get("peak")},
            )
            if deadline is not None and loop.time() >= deadline:
                break
        return 0 if heard_anything else 1
    finally:
        # Each on its own: one that fails must not leave the other stream running.
        if talking:
            await _undo(config, "talk", platform_id=args.id, on=False)
        if listening:
            await _undo(config, "stop_receive", platform_id=args.id, stream="audio_out")


async def _undo(config: StationConfig, method: str, **params: Any) -> None:
    try:
        await api_call_async(config, method, **params)
    except (RpcError, CliError) as err:
        print(f"brasidas-station: {method} failed, a stream may still run: {err}", file=sys.stderr)


async def _receiver(config: StationConfig, platform_id: str) -> dict[str, Any] | None:
    for entry in await api_call_async(config, "receivers"):
        if entry.get("platform_id") == platform_id and entry.get("stream") == "audio_out":
            return dict(entry)
    return None


def _say(args: argparse.Namespace, text: str, value: dict[str, Any]) -> None:
    print(json.dumps(value, allow_nan=False) if args.json else text, flush=True)
