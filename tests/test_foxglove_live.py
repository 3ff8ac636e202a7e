"""Foxglove, live: a real client (``@foxglove/ws-protocol`` over ``ws``, Node) subscribes to
the station's Foxglove WebSocket server over ``foxglove.sdk.v1`` (or only
``foxglove.websocket.v1``) and receives a --sim platform's LocationFix and CompressedVideo
messages, under the names the platform's own recording has."""

from __future__ import annotations

import asyncio
import base64
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from conftest import quiet_platform_config, running_station, wait_until
from mcap.reader import make_reader
from support.cli import run_cli
from support.foxglove import subscribe

from brasidas import topics
from brasidas.recording import schemas as recorded
from platformd.app import PlatformDaemon
from stationd.foxglove_live import FoxgloveLive
from stationd.foxglove_subprotocol import LEGACY

Factory = Callable[..., Awaitable[PlatformDaemon]]


def topics_of(path: Path) -> dict[str, str]:
    """A recording's topics and their schema names, as the ``mcap`` package reads them."""
    with open(path, "rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    return {
        channel.topic: summary.schemas[channel.schema_id].name
        for channel in summary.channels.values()
    }


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
    async with running_station(
        fleet_key, "foxglove.port=0", "foxglove.platform_prefix=true"
    ) as station:
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
    assert len(fixes) == 3
    assert len(video) == 3
    for fix in fixes:
        assert fix["schema"] == "foxglove.LocationFix"
        assert fix["encoding"] == "json"
        assert abs(fix["json"]["latitude"] - 37.9415) < 0.01
        assert abs(fix["json"]["longitude"] - 23.6530) < 0.01
    for frame in video:
        assert frame["schema"] == "foxglove.CompressedVideo"
        assert frame["json"]["format"] == "h264"
        assert base64.b64decode(frame["json"]["data"][:8]).startswith(b"\x00\x00")
    # The first frame a client gets is a keyframe with its SPS (NAL type 7) in front.
    first = base64.b64decode(video[0]["json"]["data"][:16])
    assert first[:5] in (b"\x00\x00\x00\x01\x67", b"\x00\x00\x00\x01\x09"), first


async def test_every_channel_the_station_advertises_is_fed(
    platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    """Commands the station sends, state changes, the velocities and motor commands telemetry
    shows: a real client subscribed to every channel advertised gets a message on each; a
    channel nothing feeds (``/pose/local``) is not advertised. One naming: each live topic
    (the default, one platform) is a topic of the platform's own recording with the same
    schema, as the ``mcap`` package reads the file ``logs ID get`` fetches, so one Foxglove
    layout works on both."""
    platform = await platform_factory(
        quiet_platform_config(
            "platform.id=rover-fa",
            "sim.enabled=true",
            "gps.enabled=true",
            "navcam.enabled=true",
            "motor.enabled=true",
            "recorder.enabled=true",
            f"recorder.dir={tmp_path / 'recordings'}",
            "recorder.chunk_seconds=0.5",
            f"map.file={tmp_path / 'map.geojson'}",
            f"autonomy.route_file={tmp_path / 'route.json'}",
        ),
        fleet_key,
    )
    required = [
        topic
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
        # The platform's recording of the same minute, fetched as an operator would, until its
        # closed chunks hold what was fed live (the writer's thread may lag under load).
        (active,) = (tmp_path / "recordings").glob("*.mcap.active")
        copy = tmp_path / "now.mcap"
        fed = {"/gps", "/pose", "/navcam", "/commands", "/state", "/motor/command"}
        recorded_topics: dict[str, str] = {}
        deadline = asyncio.get_running_loop().time() + 20
        while not fed <= recorded_topics.keys() and asyncio.get_running_loop().time() < deadline:
            code, _, err = await run_cli(
                station, "logs", "rover-fa", "get", active.name, "-o", str(copy)
            )
            assert code == 0, err
            recorded_topics = await asyncio.to_thread(topics_of, copy)
    advertised = {line["advertised"]: line["schema"] for line in lines if "advertised" in line}
    messages: dict[str, list[dict[str, Any]]] = {}
    for line in lines:
        if "topic" in line:
            messages.setdefault(line["topic"], []).append(line)
    assert set(required) <= set(advertised), advertised
    assert set(messages) == set(advertised), set(advertised) - set(messages)
    assert "/pose/local" not in advertised  # telemetry carries no local frame
    for topic, schema in {
        "/commands": "brasidas.Command",
        "/state": "brasidas.StateChange",
        "/velocity/teleop": "brasidas.Velocity",
        "/velocity/autonomy": "brasidas.Velocity",
        "/motor/command": "brasidas.Velocity",
    }.items():
        assert advertised[topic] == schema
    (command,) = messages["/commands"]
    assert command["json"]["station"] == station.ctx.config.station.id
    assert command["json"]["kind"] == "system"
    assert command["json"]["accepted"] is True
    assert command["json"]["name"] in ("10.0", "10.6")
    assert "session" not in command["json"]
    (state,) = messages["/state"]
    assert set(state["json"]) == {"what", "state", "station", "reason"}
    (motor,) = messages["/motor/command"]
    assert set(motor["json"]) == {"linear", "angular"}
    # Each live topic is a recorder channel's name and schema; those this minute's file has
    # (the ones fed while it was written) are the very same in it.
    channels = {spec.topic: spec.schema_name for spec in recorded.all_channels()}
    assert {topic: channels.get(topic) for topic in advertised} == advertised
    shared = advertised.keys() & recorded_topics.keys()
    assert fed <= shared, fed - shared
    assert {topic: recorded_topics[topic] for topic in shared} == {
        topic: advertised[topic] for topic in shared
    }


async def test_a_second_platform_is_told_apart_by_its_id(
    platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    """The default naming: the first platform has the recordings' names (``/gps``), another
    connected meanwhile is ``/rover-fz/gps``; both are served at once. The client offers only
    ``foxglove.websocket.v1`` (``FoxgloveClient``'s own, older viewers'): it connects under
    that name and decodes the SDK's messages."""
    platforms = []
    for name in ("rover-fy", "rover-fz"):
        platforms.append(
            await platform_factory(
                quiet_platform_config(
                    f"platform.id={name}",
                    "sim.enabled=true",
                    "gps.enabled=true",
                    f"map.file={tmp_path / name / 'map.geojson'}",
                    f"autonomy.route_file={tmp_path / name / 'route.json'}",
                ),
                fleet_key,
            )
        )
    async with running_station(fleet_key, "foxglove.port=0") as station:
        (live,) = [a for a in station.supervisor.actors if isinstance(a, FoxgloveLive)]
        await asyncio.wait_for(live.serving.wait(), 30)
        for name, platform in zip(("rover-fy", "rover-fz"), platforms, strict=True):
            code, _, err = await run_cli(
                station, "connect", name, "--url", platform.ctx.signaling_url
            )
            assert code == 0, err
            await wait_until(lambda name=name: name in live.platforms, 20)  # type: ignore[misc]
        lines = await subscribe(live.port, 2, "/gps", "/rover-fz/gps", offer=LEGACY)
    assert lines[0]["subprotocol"] == LEGACY
    fixes = {
        topic: [line for line in lines if line.get("topic") == topic]
        for topic in ("/gps", "/rover-fz/gps")
    }
    for topic, received in fixes.items():
        assert len(received) == 2, topic
        assert received[0]["schema"] == "foxglove.LocationFix", topic
    assert "/rover-fy/gps" not in {line.get("topic") for line in lines}
