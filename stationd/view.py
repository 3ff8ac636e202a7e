"""``brasidas-station view ID [STREAM]``: a platform's video in a native window.

The command receives the stream itself (a local GStreamer pipeline into ``autovideosink``)
and asks the platform, through the station daemon's session, to send it to this host on a
free port; it prints the glass-to-glass latency once a second, and stops the stream when it
ends (Ctrl-C, ``--seconds``). ``--sdp FILE`` instead writes an SDP description for ffplay or
VLC and starts the stream to the configured port.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
from pathlib import Path
from typing import Any

from brasidas.actor import stop_on_signals
from brasidas.codecs.jsonrpc import RpcError
from brasidas.config import StationConfig
from brasidas.media.gst import MediaError
from brasidas.media.pipeline import StreamState
from brasidas.media.video import VideoIn
from stationd.api_client import CliError, api_call_async
from stationd.media import free_udp_port, receive_host, sdp_text


def run_view(args: argparse.Namespace, config: StationConfig) -> int:
    try:
        if args.sdp:
            return asyncio.run(_write_sdp(args, config))
        return asyncio.run(_view(args, config))
    except MediaError as err:
        raise CliError(str(err)) from None


async def _platform_host(args: argparse.Namespace, config: StationConfig) -> str:
    from urllib.parse import urlsplit

    summary = await api_call_async(config, "connect", platform_id=args.id, url=args.url or "")
    return urlsplit(str(summary.get("signaling_url", ""))).hostname or ""


async def _write_sdp(args: argparse.Namespace, config: StationConfig) -> int:
    platform_host = await _platform_host(args, config)
    port = args.port or free_udp_port(receive_host(platform_host))
    answer = await api_call_async(
        config, "stream_start", platform_id=args.id, stream=args.stream, port=port
    )
    text = sdp_text(
        port,
        listen_host=receive_host(platform_host),
        name=f"Brasidas {args.id} {args.stream}",
        platform_host=platform_host or "0.0.0.0",
    )
    path = Path(args.sdp)
    await asyncio.to_thread(path.write_text, text)
    if args.json:
        print(
            json.dumps(
                {"sdp": str(path), "port": port, "stream": answer}, indent=2, allow_nan=False
            )
        )
    else:
        print(f"{path}: {args.stream} of {args.id} arrives on UDP {port} ({answer.get('state')})")
        print(f"  ffplay -protocol_whitelist file,udp,rtp -fflags nobuffer {path}")
        print(f"  stop it with: brasidas-station cmd {args.id} 10 2")
    return 0


async def _view(args: argparse.Namespace, config: StationConfig) -> int:
    if args.sink == "autovideosink" and not (
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    ):
        # autovideosink would probe DirectFB on a console, which can crash the process.
        raise CliError("no display (DISPLAY unset): use --sink fakesink, or --sdp for ffplay/VLC")
    platform_host = await _platform_host(args, config)
    streams = await api_call_async(config, "streams", platform_id=args.id)
    names = [str(s.get("name")) for s in streams]
    if args.stream not in names:
        raise CliError(f"no stream named '{args.stream}' (streams: {', '.join(names) or 'none'})")
    host = receive_host(platform_host)
    receiver = VideoIn(
        args.stream, host=host, port=args.port or free_udp_port(host), sink=args.sink
    )
    stop = stop_on_signals()
    loop = asyncio.get_running_loop()
    try:
        if await receiver.start() is StreamState.FAILED:
            raise CliError(f"cannot receive: {receiver.reason}")
        answer = await api_call_async(
            config, "stream_start", platform_id=args.id, stream=args.stream, port=receiver.port
        )
        rtcp_port = answer.get("rtcp_port")
        if isinstance(rtcp_port, int) and platform_host:
            receiver.set_feedback(platform_host, rtcp_port)  # NACKs and keyframe requests
        await receiver.follow_sender(answer)
        print(
            f"{args.id} {args.stream}: {answer.get('width')}x{answer.get('height')} "
            f"@{answer.get('framerate')} fps {answer.get('codec')} on UDP {receiver.port}",
            flush=True,
        )
        seconds = args.seconds or None
        deadline = loop.time() + seconds if seconds else None
        while not stop.is_set():
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(stop.wait(), 1.0)
            _report(args, receiver.latency_stats())
            if receiver.state is StreamState.FAILED:
                raise CliError(f"receiver failed: {receiver.reason}")
            if deadline is not None and loop.time() >= deadline:
                break
        return 0 if receiver.frames else 1
    finally:
        await receiver.stop()
        with contextlib.suppress(RpcError, CliError):
            await api_call_async(
                config,
                "stream_stop",
                platform_id=args.id,
                stream=args.stream,
                port=receiver.port,  # its own copy: the console's picture goes on
            )


def _report(args: argparse.Namespace, stats: dict[str, Any]) -> None:
    if args.json:
        print(json.dumps(stats, allow_nan=False), flush=True)
        return
    latency = stats.get("latency_ms")
    if latency is None:
        print(f"frames {stats['frames']}  latency -", flush=True)
        return
    print(
        f"frames {stats['frames']}  latency {latency:.1f} ms  "
        f"p50 {stats['latency_p50_ms']:.1f}  p99 {stats['latency_p99_ms']:.1f}",
        flush=True,
    )
