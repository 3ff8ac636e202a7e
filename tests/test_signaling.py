"""Signaling end to end over real sockets: sessions, authentication, commands, R-17."""

from __future__ import annotations

import asyncio
import json
import os
from collections.abc import Awaitable, Callable
from typing import Any

import aiohttp
import pytest
from conftest import quiet_platform_config, wait_until

from brasidas import topics
from brasidas.codecs.commands import BATTERY_MONITOR, DESCRIPTIONS, MAIN_LIGHTS, CommandCode
from brasidas.codecs.jsonrpc import CONTROL_REFUSED, RpcError
from brasidas.messages import CommandResult
from brasidas.rpc import STRANGER_MAX_BYTES, RpcClient
from platformd.app import PlatformDaemon
from platformd.commands import DuplicateCommandError, SystemCommand
from stationd.client import AuthenticationError, PlatformConnection

Factory = Callable[..., Awaitable[PlatformDaemon]]


def connection(
    daemon: PlatformDaemon, key: bytes | None, station: str = "st-1"
) -> PlatformConnection:
    return PlatformConnection(
        daemon.config.platform.id, daemon.ctx.signaling_url, station_id=station, fleet_key=key
    )


async def post(daemon: PlatformDaemon, body: bytes) -> tuple[int, Any]:
    async with (
        aiohttp.ClientSession() as session,
        session.post(daemon.ctx.signaling_url + "/rpc", data=body) as response,
    ):
        text = await response.text()
        return response.status, json.loads(text) if text else None


async def test_connect_returns_parameters_and_capabilities(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(quiet_platform_config("platform.id=rover-9"), fleet_key)
    conn = connection(daemon, fleet_key)
    await conn.open()
    try:
        assert conn.parameters["id"] == "rover-9"
        assert conn.parameters["limits"]["max_speed_kmh"] == 6.0
        assert {"streams", "velocity", "telemetry", "payload_groups"} <= set(conn.capabilities)
        assert conn.session_key is not None
        assert len(conn.session_key) == 32
        server_session = daemon.ctx.sessions.sessions[conn.session_id]
        assert server_session.session_key == conn.session_key  # derived on both ends, never sent
        assert (await conn.call("heartbeat"))["manual_override"] is False
    finally:
        await conn.close()
    assert daemon.ctx.sessions.sessions == {}


async def test_a_capability_section_has_one_owner(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    """A second subsystem cannot take over a section of connect's capabilities; its owner
    removes it, and a station connecting then sees what is registered at that moment."""
    daemon = await platform_factory(quiet_platform_config(), fleet_key)
    with pytest.raises(ValueError, match="'telemetry' is already registered"):
        daemon.ctx.capabilities.register("telemetry", lambda: {"rate_hz": 0})
    remove = daemon.ctx.capabilities.register("winch", lambda: {"max_pull_n": 900})
    conn = connection(daemon, fleet_key)
    await conn.open()
    try:
        assert conn.capabilities["winch"] == {"max_pull_n": 900}
        assert conn.capabilities["telemetry"]["push"] is True
    finally:
        await conn.close()
    remove()
    assert "winch" not in daemon.ctx.capabilities.describe()


async def test_wrong_fleet_key_is_refused_and_counted(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(quiet_platform_config(), fleet_key)
    conn = connection(daemon, os.urandom(32))
    with pytest.raises(AuthenticationError, match="unauthorized"):
        await conn.open()
    assert daemon.ctx.sessions.auth_failures == 1
    assert daemon.ctx.sessions.sessions == {}


async def test_station_refuses_impostor_platform(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    # A platform with another key cannot produce the accept proof: the station must not trust it.
    impostor = await platform_factory(quiet_platform_config(), os.urandom(32))
    conn = connection(impostor, fleet_key)
    with pytest.raises(AuthenticationError):
        await conn.open()


async def test_replayed_challenge_is_refused(platform_factory: Factory, fleet_key: bytes) -> None:
    from brasidas.security import connect_proof

    daemon = await platform_factory(quiet_platform_config(), fleet_key)
    async with RpcClient(daemon.ctx.signaling_url + "/rpc/ws") as client:
        nonce = (await client.call("challenge"))["nonce"]
        proof = connect_proof(fleet_key, "brasidas-1", "st", nonce, "abc")
        params = {"station_id": "st", "nonce": nonce, "station_nonce": "abc", "proof": proof}
        first = await client.call("connect", params)
        with pytest.raises(RpcError) as err:
            await client.call("connect", params)
        assert err.value.code == -32001
        assert first["session"] in daemon.ctx.sessions.sessions
        assert len(daemon.ctx.sessions.sessions) == 1


async def test_http_post_errors(platform_factory: Factory, fleet_key: bytes) -> None:
    daemon = await platform_factory(quiet_platform_config(), fleet_key)
    status, body = await post(
        daemon, b'{"jsonrpc":"2.0","id":1,"method":"get_platform_parameters"}'
    )
    assert status == 401
    assert body["error"]["code"] == -32001
    status, body = await post(daemon, b"{garbage")
    assert status == 200
    assert body["error"]["code"] == -32700
    status, body = await post(
        daemon,
        b'{"jsonrpc":"2.0","id":1,"method":"x","params":"' + b"a" * STRANGER_MAX_BYTES + b'"}',
    )  # before a session, a stranger's limit; with one, signaling.max_request_bytes
    assert status == 413
    assert f"the limit is {STRANGER_MAX_BYTES} bytes" in body["error"]["message"]
    status, body = await post(daemon, b'{"jsonrpc":"2.0","method":"challenge"}')
    assert status == 204
    # Still serving after all that.
    status, body = await post(daemon, b'{"jsonrpc":"2.0","id":2,"method":"challenge"}')
    assert status == 200
    assert body["result"]["platform_id"] == "brasidas-1"
    counters = daemon.ctx.rpc.counters
    assert counters["unauthorized"] == 1
    assert counters["parse_errors"] == 1


async def test_oversize_websocket_message_is_refused(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(quiet_platform_config(), fleet_key)
    async with RpcClient(daemon.ctx.signaling_url + "/rpc/ws") as client:
        with pytest.raises((RpcError, ConnectionError)):
            await client.call("challenge", {"pad": "a" * 70000}, timeout=2)
    async with RpcClient(daemon.ctx.signaling_url + "/rpc/ws") as client:
        assert (await client.call("challenge"))["auth"] == "hmac-sha256"


async def test_hostile_websocket_messages_get_errors_and_the_socket_keeps_serving(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(quiet_platform_config(), fleet_key)
    async with (
        aiohttp.ClientSession() as session,
        session.ws_connect(daemon.ctx.signaling_url + "/rpc/ws") as ws,
    ):
        for hostile in ("[" * 4_000, "{garbage", '{"jsonrpc":"2.0","id":1}', "[]"):
            await ws.send_str(hostile)
            answer = json.loads((await ws.receive(timeout=5)).data)
            assert answer["error"]["code"] in (-32700, -32600), hostile[:20]
        await ws.send_str("[" * 60_000)  # a stranger's: over 4 KiB, never parsed
        assert json.loads((await ws.receive(timeout=5)).data)["error"]["code"] == -32004
        await ws.send_bytes(b"\xff\xfe")
        assert json.loads((await ws.receive(timeout=5)).data)["error"]["code"] == -32700
        await ws.send_str('{"jsonrpc":"2.0","id":9,"method":"challenge"}')
        assert json.loads((await ws.receive(timeout=5)).data)["id"] == 9
    assert daemon.ctx.rpc.counters["parse_errors"] == 3


async def test_system_commands_reach_their_owner_and_answer(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(quiet_platform_config(), fleet_key)
    seen: list[SystemCommand] = []

    async def lights(command: SystemCommand) -> CommandResult:
        seen.append(command)
        return CommandResult(True, result={"main": command.payload})

    async def turret(command: SystemCommand) -> CommandResult:
        return CommandResult(True, result={"fired": command.payload})

    unregister = daemon.ctx.commands.register("test-lights", {MAIN_LIGHTS: lights})
    daemon.ctx.commands.register("turret", {CommandCode(105, 2): turret})
    conn = connection(daemon, fleet_key)
    await conn.open()
    try:
        answer = await conn.call("issue_system_command", group=10, command=6, payload="ON")
        assert answer == {"accepted": True, "reason": "", "result": {"main": "ON"}}
        assert seen[0].session_id == conn.session_id
        assert seen[0].session.station_id == "st-1"
        assert conn.capabilities["payload_groups"] == [105]
        assert (await conn.call("set_lights", which="main", on=False))["result"] == {"main": "OFF"}
        answer = await conn.call("issue_system_command", group=105, command=2, payload="x")
        assert answer == {"accepted": True, "reason": "", "result": {"fired": "x"}}
        unregister()
        answer = await conn.call("issue_system_command", group=10, command=6, payload="ON")
        assert answer["accepted"] is False
        assert "not available" in answer["reason"]
        answer = await conn.call("issue_system_command", group=105, command=3, payload="")
        assert answer["accepted"] is False
        assert "not available" in answer["reason"]
        answer = await conn.call("issue_system_command", group=91, command=0, payload="")
        assert answer["accepted"] is False
        assert "station-only" in answer["reason"]
        with pytest.raises(RpcError) as err:
            await conn.call("issue_system_command", group=42, command=1, payload="")
        assert err.value.code == -32602
        assert "unknown command code 42.1" in err.value.message
        with pytest.raises(RpcError) as err:
            await conn.call("issue_system_command", group="10", command=6)
        assert err.value.code == -32602
    finally:
        await conn.close()


async def test_every_platform_code_has_one_owner_in_sim(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(
        quiet_platform_config("sim.enabled=true", "motor.enabled=true"),
        fleet_key,
    )
    await wait_until(lambda: all(daemon.ctx.commands.owner(code) for code in DESCRIPTIONS))
    owners = {str(code): daemon.ctx.commands.owner(code) for code in DESCRIPTIONS}
    assert owners == {
        "10.0": "mode",
        "10.1": "media",
        "10.2": "media",
        "10.3": "media",
        "10.5": "media",
        "10.6": "motor",
        "10.7": "motor",
        "10.8": "patrol",
        "10.9": "media",
        "10.10": "media",
        "20.0": "telemetry",
        "20.4": "motor",
    }
    with pytest.raises(DuplicateCommandError):
        daemon.ctx.commands.register("impostor", {MAIN_LIGHTS: daemon_lights(daemon)})


def daemon_lights(daemon: PlatformDaemon) -> Any:
    async def handler(command: SystemCommand) -> CommandResult:
        return CommandResult(True)

    return handler


async def test_authority_is_asked_for_every_way_a_command_comes_in(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    """Where command authority (issue 13) plugs in: issue_system_command, set_manual_override
    and set_lights all pass the router's one hook, with the calling session."""
    daemon = await platform_factory(quiet_platform_config(), fleet_key)
    asked: list[tuple[str, str | None]] = []

    def observers_refused(command: SystemCommand) -> str | None:
        session = command.session
        asked.append((str(command.code), session.station_id if session else None))
        return None if session and session.station_id == "holder" else "held by holder"

    daemon.ctx.commands.authorize = observers_refused
    daemon.ctx.commands.register("lights", {MAIN_LIGHTS: daemon_lights(daemon)})
    observer, holder = (
        connection(daemon, fleet_key, "observer"),
        connection(daemon, fleet_key, "holder"),
    )
    await observer.open()
    await holder.open()
    try:
        answer = await observer.call("issue_system_command", group=10, command=6, payload="ON")
        assert answer == {"accepted": False, "reason": "held by holder", "result": None}
        with pytest.raises(RpcError) as refusal:
            await observer.call("set_manual_override", engaged=True)
        assert refusal.value.code == CONTROL_REFUSED
        assert "held by holder" in str(refusal.value)
        assert (await observer.call("set_lights", which="main", on=True))["accepted"] is False
        assert daemon.bus.last(topics.OVERRIDE_STATE).engaged is False
        assert await holder.call("set_manual_override", engaged=True) is True
        assert (await holder.call("set_lights", which="main", on=True))["accepted"] is True
        assert asked == [
            ("10.6", "observer"),
            ("10.0", "observer"),
            ("10.6", "observer"),
            ("10.0", "holder"),
            ("10.6", "holder"),
        ]
    finally:
        await observer.close()
        await holder.close()


async def test_slow_owner_times_out_with_a_reason(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(
        quiet_platform_config("signaling.command_timeout=0.2"), fleet_key
    )
    never = asyncio.Event()

    async def sleepy(command: SystemCommand) -> CommandResult:
        await never.wait()
        return CommandResult(True)

    daemon.ctx.commands.register("sleepy", {BATTERY_MONITOR: sleepy})
    conn = connection(daemon, fleet_key)
    await conn.open()
    try:
        answer = await conn.call("issue_system_command", group=20, command=4, payload="True")
        assert answer["accepted"] is False
        assert "not answered by sleepy in 0.2 s" in answer["reason"]
    finally:
        await conn.close()


async def test_manual_override_is_exclusive_and_released_on_timeout(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(
        quiet_platform_config(
            "signaling.session_timeout=0.5",
            "signaling.heartbeat_interval=10",
            "failsafe.hold_after=0.2",
            "failsafe.release_after=0.3",
        ),
        fleet_key,
    )
    states: list[bool] = []
    daemon.bus.subscribe(topics.OVERRIDE_STATE, lambda s: states.append(s.engaged))
    first, second = connection(daemon, fleet_key, "first"), connection(daemon, fleet_key, "second")
    await first.open()
    await second.open()
    try:
        assert await first.call("set_manual_override", engaged=True) is True
        # Refused with the holder's name (issue 19, item 9), not a bare false.
        with pytest.raises(RpcError) as refusal:
            await second.call("set_manual_override", engaged=True)
        assert refusal.value.code == CONTROL_REFUSED
        assert "control held by station first" in str(refusal.value)
        refused = await second.call("issue_system_command", group=10, command=0, payload="False")
        assert refused["accepted"] is False
        assert "control held by station first" in refused["reason"]
        report = await second.call("get_telemetry_report")
        assert report["override"]["mode"] == "teleop"
        # "first" goes silent (heartbeats every 10 s): the failsafe ladder holds and releases
        # the override (0.3 s), then its session times out (0.5 s).
        await wait_until(lambda: first.session_id not in daemon.ctx.sessions.sessions)
        assert states[-1] is False
    finally:
        await first.close()
        await second.close()
    assert states[:2] == [False, True]


async def test_closing_the_websocket_ends_the_session_and_the_override(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(quiet_platform_config(), fleet_key)
    conn = connection(daemon, fleet_key)
    await conn.open()
    assert await conn.call("set_manual_override", engaged=True) is True
    await conn._client.close()  # the link drops without a goodbye
    await wait_until(lambda: not daemon.bus.last(topics.OVERRIDE_STATE).engaged)
    assert daemon.ctx.sessions.sessions == {}
    await conn.close()


async def test_insecure_platform_needs_no_key(platform_factory: Factory) -> None:
    daemon = await platform_factory(quiet_platform_config(), None)
    conn = connection(daemon, None)
    await conn.open()
    try:
        assert conn.session_key is None
        assert (await conn.call("get_velocity_connection_info"))["auth"] == "none"
    finally:
        await conn.close()


async def test_keyless_station_refuses_secure_platform(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(quiet_platform_config(), fleet_key)
    with pytest.raises(AuthenticationError, match="requires a fleet key"):
        await connection(daemon, None).open()
