"""Command authority (issue 13): two stations on one --sim platform, over real sockets.

One holds control; the other observes (its own copy of the video, telemetry) and is refused
everything else with the holder's station id, until it takes control with ``force``.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

import pytest
from conftest import free_udp_port, quiet_platform_config, running_station, wait_until
from support.cli import run_cli

from brasidas import topics
from brasidas.codecs.commands import CommandCode
from brasidas.codecs.jsonrpc import (
    CONTROL_REFUSED,
    REQUEST_TOO_LARGE,
    TIMEOUT,
    UNAUTHORIZED,
    UNAVAILABLE,
    RpcError,
)
from brasidas.media.video import VideoIn
from brasidas.messages import CommandResult, OverrideState
from platformd.app import PlatformDaemon
from platformd.commands import SystemCommand
from stationd.client import PlatformConnection

Factory = Callable[..., Awaitable[PlatformDaemon]]


@pytest.fixture
async def receivers() -> AsyncIterator[tuple[VideoIn, VideoIn]]:
    first = VideoIn("rx-a", port=free_udp_port(), host="127.0.0.1")
    second = VideoIn("rx-b", port=free_udp_port(), host="127.0.0.1")
    await first.start()
    await second.start()
    try:
        yield first, second
    finally:
        await first.stop()
        await second.stop()


async def station(daemon: PlatformDaemon, key: bytes, name: str) -> PlatformConnection:
    conn = PlatformConnection(
        daemon.config.platform.id, daemon.ctx.signaling_url, station_id=name, fleet_key=key
    )
    await conn.open()
    return conn


async def command(
    conn: PlatformConnection, group: int, code: int, payload: str = ""
) -> dict[str, Any]:
    answer: dict[str, Any] = await conn.call(
        "issue_system_command", group=group, command=code, payload=payload
    )
    return answer


async def frames_arrive(stream: VideoIn, count: int = 5) -> None:
    before = stream.frames
    await wait_until(lambda: stream.frames >= before + count, timeout=15.0)


async def test_observer_is_refused_control_and_keeps_its_own_video(
    platform_factory: Factory, fleet_key: bytes, receivers: tuple[VideoIn, VideoIn]
) -> None:
    rx_a, rx_b = receivers
    daemon = await platform_factory(
        quiet_platform_config(
            "sim.enabled=true",
            "navcam.enabled=true",
            "motor.enabled=true",
            "signaling.heartbeat_interval=0.2",
        ),
        fleet_key,
    )
    overrides: list[OverrideState] = []
    daemon.bus.subscribe(topics.OVERRIDE_STATE, overrides.append)
    a = await station(daemon, fleet_key, "alpha")
    b = await station(daemon, fleet_key, "bravo")
    lost: list[str | None] = []
    a.on_control_lost = lost.append
    try:
        # Both see video at once, each at its own destination.
        await a.call("start_stream", name="navcam", port=rx_a.port)
        await b.call("start_stream", name="navcam", port=rx_b.port)
        await asyncio.gather(frames_arrive(rx_a), frames_arrive(rx_b))

        assert (await command(a, 10, 0, "True"))["accepted"]
        for group, code, payload in ((10, 0, "True"), (10, 6, "ON"), (10, 5, "navcam=10")):
            refused = await command(b, group, code, payload)
            assert refused["accepted"] is False
            assert "control held by station alpha" in refused["reason"]
        with pytest.raises(RpcError) as info:
            await b.call("pause_stream", name="navcam")
        assert info.value.code == CONTROL_REFUSED
        assert "alpha" in info.value.message
        assert await b.call("set_lights", which="main", on=True) == {
            "accepted": False,
            "reason": "main lights refused: control held by station alpha",
            "result": None,
        }
        # The observer's stop ends its own copy only: the controller's video goes on.
        assert (await b.call("stop_stream", name="navcam"))["state"] == "playing"
        await frames_arrive(rx_a)
        # ...and stopping everything (10.2) from the observer cannot stop it either.
        await command(b, 10, 2)
        await frames_arrive(rx_a)
        assert daemon.ctx.authority.station_id == "alpha"
        assert daemon.ctx.commands.counters["refused"] == 4

        # Takeover: the override moves to bravo, alpha is told at its next heartbeat.
        heartbeat = await a.call("heartbeat")
        assert heartbeat["control"] is True
        assert heartbeat["controller"] == "alpha"
        await wait_until(lambda: a.control)  # its heartbeats say it holds control
        taken = await command(b, 10, 0, "state=True,force=yes")
        assert taken["accepted"], taken
        assert overrides[-2:] == [
            OverrideState(False),
            OverrideState(True, b.session_id, "bravo"),
        ]
        await wait_until(lambda: lost == ["bravo"])
        assert a.control is False
        assert a.controller == "bravo"
        refused = await command(a, 10, 6, "ON")
        assert "control held by station bravo" in refused["reason"]
        assert daemon.ctx.authority.counters["takeovers"] == 1
    finally:
        await a.close()
        await b.close()


async def test_control_is_freed_when_its_session_ends(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(quiet_platform_config(), fleet_key)
    a = await station(daemon, fleet_key, "alpha")
    b = await station(daemon, fleet_key, "bravo")
    try:
        assert (await command(a, 10, 0, "True"))["accepted"]
        assert not (await command(b, 10, 0, "True"))["accepted"]
        # A forced release is not a thing: force only takes control to engage.
        assert not (await command(b, 10, 0, "state=False,force=yes"))["accepted"]
        await a.close()
        await wait_until(lambda: daemon.ctx.authority.controller is None)
        assert (await command(b, 10, 0, "True"))["accepted"]
        assert daemon.ctx.authority.station_id == "bravo"
    finally:
        await a.close()
        await b.close()


async def test_only_the_controller_changes_the_patrol(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    """The map, the route and the patrol are control: an observer reads them, changes none."""
    daemon = await platform_factory(
        quiet_platform_config("sim.enabled=true", "motor.enabled=true", "gps.enabled=true"),
        fleet_key,
    )
    a = await station(daemon, fleet_key, "alpha")
    b = await station(daemon, fleet_key, "bravo")
    try:
        area = await a.call("get_map")
        route = [[w["lat"], w["lon"]] for w in area["route"]]
        assert (await a.call("set_waypoints", waypoints=route[:3]))["waypoints"]  # claims control
        assert daemon.ctx.authority.station_id == "alpha"
        for method, params in (
            ("set_waypoints", {"waypoints": route}),
            ("patrol_start", {}),
            ("patrol_stop", {}),
            ("load_map", {"map": area["map"]}),
            ("update_map", {"remove": ["shed"]}),
        ):
            with pytest.raises(RpcError) as info:
                await b.call(method, **params)
            assert info.value.code == CONTROL_REFUSED, method
            assert f"{method} refused: control held by station alpha" in info.value.message
        assert len((await b.call("get_map"))["route"]) == 3  # unchanged, and readable
        assert (await b.call("get_patrol"))["waypoints"] == 3
        arming = daemon.ctx.arming
        assert arming is not None  # a start arms through the pre-arm checks (issue 27)
        await wait_until(lambda: not arming.reasons(), 20)
        assert (await a.call("patrol_start"))["state"] != "idle"
        assert (await a.call("patrol_stop"))["state"] == "stopped"
    finally:
        await a.close()
        await b.close()


async def test_a_refused_override_and_a_timed_out_command_answer_different_codes(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    """Control refused (-32005) is not a timeout (-32003): a station retrying a timeout must
    not read an observer's refusal as one, nor the other way round."""
    daemon = await platform_factory(
        quiet_platform_config("signaling.command_timeout=10"), fleet_key
    )
    release = asyncio.Event()

    async def stuck(command: SystemCommand) -> CommandResult:
        await release.wait()
        return CommandResult(True)

    unregister = daemon.ctx.commands.register("stuck", {CommandCode(40, 1): stuck})
    holder = PlatformConnection(
        daemon.config.platform.id,
        daemon.ctx.signaling_url,
        station_id="alpha",
        fleet_key=fleet_key,
        timeout=0.5,
    )
    await holder.open()
    observer = await station(daemon, fleet_key, "bravo")
    try:
        assert await holder.call("set_manual_override", engaged=True) is True
        with pytest.raises(RpcError) as refused:
            await observer.call("set_manual_override", engaged=True)
        assert refused.value.code == CONTROL_REFUSED
        assert "alpha" in refused.value.message
        with pytest.raises(RpcError) as timed_out:
            await holder.call("issue_system_command", group=40, command=1, payload="")
        assert timed_out.value.code == TIMEOUT
        assert refused.value.code != timed_out.value.code
        assert len({CONTROL_REFUSED, TIMEOUT, UNAUTHORIZED, UNAVAILABLE, REQUEST_TOO_LARGE}) == 5
    finally:
        release.set()
        unregister()
        await observer.close()
        await holder.close()


async def test_the_station_cli_says_control_refused_naming_the_holder(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    """Through the station daemon: the platform's refusal keeps its code and the CLI says
    what it is (not 'timed out', not a bare message)."""
    daemon = await platform_factory(
        quiet_platform_config("sim.enabled=true", "motor.enabled=true", "gps.enabled=true"),
        fleet_key,
    )
    holder = await station(daemon, fleet_key, "alpha")
    try:
        assert (await command(holder, 10, 0, "True"))["accepted"]
        async with running_station(fleet_key, "station.id=bravo") as observer:
            pid, url = daemon.config.platform.id, daemon.ctx.signaling_url
            code, _, err = await run_cli(observer, "connect", pid, "--url", url)
            assert code == 0, err
            code, _, err = await run_cli(observer, "patrol", pid, "stop")
        assert code == 1
        # The in-process daemons' log lines share stderr ("no GPS fix yet"): the CLI's is one.
        assert (
            "brasidas-station: control refused: patrol_stop refused: control held by station "
            "alpha ('movrd ID on --force' takes control)"
        ) in err.splitlines()
    finally:
        await holder.close()
