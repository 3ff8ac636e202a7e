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

from conftest import quiet_platform_config, running_station, wait_until
from support.cli import run_cli

from brasidas import topics
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
    except TimeoutError:
        process.terminate()  # the client says what it still misses
        _out, err = await process.communicate()
        raise AssertionError(f"the client timed out: {err.decode()[-1500:]}") from None
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


async def test_every_channel_the_station_advertises_is_fed(
    platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    """Commands the station sends, state changes, the velocities and motor commands telemetry
    shows: a real client subscribed to every channel advertised gets a message on each; a
    channel nothing feeds (``/pose/local``) is not advertised."""
    platform = await platform_factory(
        quiet_platform_config(
            "platform.id=rover-fa",
            "sim.enabled=true",
            "gps.enabled=true",
            "navcam.enabled=true",
            "motor.enabled=true",
            f"map.file={tmp_path / 'map.geojson'}",
            f"autonomy.route_file={tmp_path / 'route.json'}",
        ),
        fleet_key,
    )
    required = [
        f"/rover-fa{topic}"
        for topic in (
            "/gps",
            "/pose",
            "/navcam",
            "/route",
            "/commands",
            "/state",
            "/velocity/teleop",
            "/velocity/autonomy",
            "/motor/command",
            "/telemetry/motion",
            "/telemetry/override",
        )
    ]
    async with running_station(fleet_key, "foxglove.port=0") as station:
        (live,) = [a for a in station.supervisor.actors if isinstance(a, FoxgloveLive)]
        await asyncio.wait_for(live.serving.wait(), 30)
        code, _, err = await run_cli(
            station, "connect", "rover-fa", "--url", platform.ctx.signaling_url
        )
        assert code == 0, err
        controller = topics.CONTROLLER_STATUS  # the override needs the motors
        await wait_until(lambda: getattr(platform.bus.last(controller), "connected", False), 20)
        client = asyncio.create_task(subscribe(live.port, 1, "--all", *required))
        try:
            engaged = False
            # The operator drives and switches lights until the client has had everything:
            # commands sent, override and mode changes (a later subscriber misses earlier ones).
            while not client.done():
                engaged = not engaged
                for args in (("movrd", "rover-fa", "on" if engaged else "off"),
                             ("lights", "rover-fa", "main", "on" if engaged else "off")):  # fmt: skip
                    code, out, err = await run_cli(station, *args)
                    assert code == 0, out + err
                await asyncio.wait([client], timeout=0.5)
            lines = await client
        finally:
            client.cancel()
    advertised = {line["advertised"]: line["schema"] for line in lines if "advertised" in line}
    messages: dict[str, list[dict[str, Any]]] = {}
    for line in lines:
        if "topic" in line:
            messages.setdefault(line["topic"], []).append(line)
    assert set(required) <= set(advertised), advertised
    assert set(messages) == set(advertised), set(advertised) - set(messages)
    assert "/rover-fa/pose/local" not in advertised  # telemetry carries no local frame
    for topic, schema in {
        "/commands": "brasidas.Command",
        "/state": "brasidas.StateChange",
        "/velocity/teleop": "brasidas.Velocity",
        "/velocity/autonomy": "brasidas.Velocity",
        "/motor/command": "brasidas.Velocity",
    }.items():
        assert advertised[f"/rover-fa{topic}"] == schema
    (command,) = messages["/rover-fa/commands"]
    assert command["json"]["station"] == station.ctx.config.station.id
    assert command["json"]["kind"] == "system" and command["json"]["accepted"] is True
    assert command["json"]["name"] in ("10.0", "10.6") and "session" not in command["json"]
    (state,) = messages["/rover-fa/state"]
    assert set(state["json"]) == {"what", "state", "station", "reason"}
    (motor,) = messages["/rover-fa/motor/command"]
    assert set(motor["json"]) == {"linear", "angular"}


async def test_live_topics_can_be_named_as_recorded_so_one_layout_fits_both(
    platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    """``foxglove.platform_prefix = false``: ``/gps`` live, as in a recording (one robot)."""
    from brasidas.recording import schemas as recorded

    platform = await platform_factory(
        quiet_platform_config(
            "platform.id=rover-fy",
            "sim.enabled=true",
            "gps.enabled=true",
            f"map.file={tmp_path / 'map.geojson'}",
            f"autonomy.route_file={tmp_path / 'route.json'}",
        ),
        fleet_key,
    )
    async with running_station(
        fleet_key, "foxglove.port=0", "foxglove.platform_prefix=false"
    ) as station:
        (live,) = [a for a in station.supervisor.actors if isinstance(a, FoxgloveLive)]
        await asyncio.wait_for(live.serving.wait(), 30)
        code, _, err = await run_cli(
            station, "connect", "rover-fy", "--url", platform.ctx.signaling_url
        )
        assert code == 0, err
        lines = await subscribe(live.port, 2, "/gps")
    fixes = [line for line in lines if line.get("topic") == "/gps"]
    assert len(fixes) == 2 and fixes[0]["schema"] == "foxglove.LocationFix"
    assert recorded.GPS.topic == "/gps"  # the recorder's name for the same channel
