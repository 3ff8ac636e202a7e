"""Foxglove, live (issue 23): a real client (``@foxglove/ws-protocol`` over ``ws``, Node)
subscribes to the station's Foxglove WebSocket server over ``foxglove.sdk.v1`` and receives a
--sim platform's LocationFix and CompressedVideo messages."""

from __future__ import annotations

import asyncio
import base64
import json
import shutil
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from conftest import quiet_platform_config, running_station
from test_station import run_cli

from platformd.app import PlatformDaemon
from stationd.foxglove_live import FoxgloveLive

Factory = Callable[..., Awaitable[PlatformDaemon]]
CLIENT = Path(__file__).parent / "foxglove_client"
"""The client script; its packages are the repository's (package.json, ``make deps``)."""
NODE = shutil.which("node")


async def subscribe(port: int, count: int, *topics: str) -> list[dict[str, Any]]:
    """Run the Node client until it has ``count`` messages of every topic; its JSON lines."""
    assert NODE is not None, "no node: `make deps` installs it"
    process = await asyncio.create_subprocess_exec(
        NODE,
        str(CLIENT / "subscribe.cjs"),
        f"ws://127.0.0.1:{port}",
        str(count),
        *topics,
        cwd=CLIENT,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    try:
        out, err = await asyncio.wait_for(process.communicate(), 60)
    finally:
        if process.returncode is None:
            process.kill()
            await process.wait()
    assert process.returncode == 0, err.decode()
    return [json.loads(line) for line in out.decode().splitlines() if line.strip()]


async def test_a_foxglove_client_receives_location_fixes_and_compressed_video(
    platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    platform = await platform_factory(
        quiet_platform_config(
            "platform.id=rover-fx",
            "sim.enabled=true",
            "gps.enabled=true",
            "navcam.enabled=true",
            f"map.file={tmp_path / 'map.geojson'}",
            f"autonomy.route_file={tmp_path / 'route.json'}",
        ),
        fleet_key,
    )
    async with running_station(fleet_key, "foxglove.port=0") as station:
        (live,) = [a for a in station.supervisor.actors if isinstance(a, FoxgloveLive)]
        await asyncio.wait_for(live.serving.wait(), 30)
        assert live.port not in (0, 8766)
        code, _, err = await run_cli(
            station, "connect", "rover-fx", "--url", platform.ctx.signaling_url
        )
        assert code == 0, err

        lines = await subscribe(live.port, 3, "/rover-fx/gps", "/rover-fx/navcam")
    assert lines[0]["subprotocol"] == "foxglove.sdk.v1"
    messages = [line for line in lines if "topic" in line]
    fixes = [m for m in messages if m["topic"] == "/rover-fx/gps"]
    video = [m for m in messages if m["topic"] == "/rover-fx/navcam"]
    assert len(fixes) == 3 and len(video) == 3
    for fix in fixes:
        assert fix["schema"] == "foxglove.LocationFix" and fix["encoding"] == "json"
        assert abs(fix["json"]["latitude"] - 37.9415) < 0.01
        assert abs(fix["json"]["longitude"] - 23.6530) < 0.01
    for frame in video:
        assert frame["schema"] == "foxglove.CompressedVideo" and frame["json"]["format"] == "h264"
        assert base64.b64decode(frame["json"]["data"][:8]).startswith(b"\x00\x00")
    # The first frame a client gets is a keyframe with its SPS (NAL type 7) in front.
    first = base64.b64decode(video[0]["json"]["data"][:16])
    assert first[:5] in (b"\x00\x00\x00\x01\x67", b"\x00\x00\x00\x01\x09"), first
