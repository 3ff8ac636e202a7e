"""The station daemon and the operator's CLI against a real platform on loopback."""

from __future__ import annotations

import asyncio
import json
from collections.abc import Awaitable, Callable

import pytest
from conftest import free_tcp_port, quiet_platform_config, wait_until
from support.cli import run_cli

from brasidas import topics
from brasidas.codecs.jsonrpc import RpcError
from brasidas.config import StationConfig, load_config
from brasidas.messages import PlatformLink
from platformd.app import PlatformDaemon
from stationd import cli
from stationd.daemon import StationDaemon

Factory = Callable[..., Awaitable[PlatformDaemon]]


async def test_connect_movrd_lights_and_commands_through_the_daemon(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes
) -> None:
    platform = await platform_factory(quiet_platform_config("platform.id=rover-3"), fleet_key)
    url = platform.ctx.signaling_url

    code, out, _ = await run_cli(station, "connect", "rover-3", "--url", url)
    assert code == 0
    assert "rover-3" in out
    assert "velocity" in out
    assert "override   disengaged" in out

    code, out, _ = await run_cli(station, "movrd", "rover-3", "on")
    assert (code, out.strip()) == (0, 'acknowledged {"engaged": true}')
    assert platform.bus.last(topics.OVERRIDE_STATE).station_id == "station-1"

    code, out, _ = await run_cli(station, "lights", "rover-3", "main", "on", "--json")
    answer = json.loads(out)
    # No motor controller on this test platform: rejected, with the reason, and exit 1.
    assert code == 1
    assert answer["accepted"] is False
    assert "main lights" in answer["reason"]

    code, _, err = await run_cli(station, "cmd", "rover-3", "42", "7")
    assert code == 1
    assert "unknown command code 42.7" in err

    code, out, _ = await run_cli(station, "status", "rover-3", "--json")
    status = json.loads(out)
    assert code == 0
    assert status["report"]["override"]["mode"] == "teleop"
    assert status["connected"] is True

    code, out, _ = await run_cli(station, "disconnect", "rover-3")
    assert code == 0
    # Ending the session releases the override on the platform.
    await wait_until(lambda: not platform.bus.last(topics.OVERRIDE_STATE).engaged)


async def test_station_shutdown_releases_the_override(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    platform = await platform_factory(quiet_platform_config(), fleet_key)
    config = load_config(StationConfig, None, ["station.api_port=0"])
    station = StationDaemon(config, fleet_key)
    await station.start()
    try:
        code, _, _ = await run_cli(
            station, "connect", "brasidas-1", "--url", platform.ctx.signaling_url
        )
        assert code == 0
        code, _, _ = await run_cli(station, "movrd", "brasidas-1", "on")
        assert code == 0
    finally:
        await station.stop()
    await wait_until(lambda: not platform.bus.last(topics.OVERRIDE_STATE).engaged)
    assert platform.ctx.sessions.sessions == {}


async def test_no_session_is_opened_once_the_station_is_stopping(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes
) -> None:
    """Other actors run on while the stop hooks do: one asking for a platform then (Foxglove
    live fetching a grid) opened a session nothing closed, its heartbeat task left running."""
    platform = await platform_factory(quiet_platform_config(), fleet_key)
    manager = station.ctx.connection_manager
    assert manager is not None
    url = platform.ctx.signaling_url
    opening = asyncio.create_task(manager.ensure("brasidas-1", url))
    await asyncio.sleep(0)  # under way: past the checks, waiting on the platform
    await manager.async_stop()
    for attempt in (opening, manager.ensure("brasidas-1", url)):
        with pytest.raises(RpcError, match="stopping"):
            await attempt
    assert station.ctx.connections == {}
    await wait_until(lambda: platform.ctx.sessions.sessions == {})
    assert not [t for t in asyncio.all_tasks() if t.get_name().startswith("heartbeat:")]


async def test_platform_going_away_is_noticed(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes
) -> None:
    platform = await platform_factory(quiet_platform_config(), fleet_key)
    opened: list[PlatformLink] = []
    lost: list[PlatformLink] = []
    station.bus.subscribe(topics.PLATFORM_CONNECTED, opened.append)
    station.bus.subscribe(topics.PLATFORM_DISCONNECTED, lost.append)
    code, _, _ = await run_cli(
        station, "connect", "brasidas-1", "--url", platform.ctx.signaling_url
    )
    assert code == 0
    session_id = station.ctx.connections["brasidas-1"].session_id
    assert opened == [PlatformLink("brasidas-1", session_id)]
    await platform.stop()
    await wait_until(lambda: [link.platform_id for link in lost] == ["brasidas-1"])
    assert lost[0].session_id == session_id
    assert lost[0].reason
    assert station.ctx.connections == {}
    code, _, err = await run_cli(station, "movrd", "brasidas-1", "on")
    assert code == 1
    assert "brasidas-1" in err


async def test_unknown_platform_and_absent_daemon_give_clear_errors(station: StationDaemon) -> None:
    code, _, err = await run_cli(station, "movrd", "ghost", "on")
    assert code == 1
    assert "ghost" in err
    code, _, err = await run_cli(
        station, "connect", "ghost", "--url", f"http://127.0.0.1:{free_tcp_port()}"
    )
    assert code == 1
    assert "cannot connect" in err

    def absent() -> int:
        return cli.main(["status", "x", "--set", f"station.api_port={free_tcp_port()}"])

    assert await asyncio.to_thread(absent) == 1


def test_keygen_writes_a_private_key_once(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "k" / "fleet.key"
    assert cli.main(["keygen", "--path", str(path)]) == 0
    assert path.stat().st_mode & 0o777 == 0o600
    assert len(bytes.fromhex(path.read_text().strip())) == 32
    assert cli.main(["keygen", "--path", str(path)]) == 1
    assert "exists" in capsys.readouterr().err
