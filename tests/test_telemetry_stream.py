"""Telemetry end to end: a platform pushing to a station daemon over real UDP on loopback."""

from __future__ import annotations

import socket
from collections.abc import AsyncIterator, Awaitable, Callable

import pytest
from conftest import quiet_platform_config, wait_until

from brasidas import topics
from brasidas.codecs.jsonrpc import INVALID_PARAMS, RpcError
from brasidas.codecs.telemetry import MAX_DATAGRAM, VERSION, TelemetryDecoder, TelemetryEncoder
from brasidas.codecs.telemetry_schema import (
    SCHEMA_VERSION,
    Computer,
    Lights,
    Override,
    Snapshot,
    snapshot_to_wire,
)
from brasidas.config import StationConfig, load_config
from brasidas.messages import LightsState, PlatformHealth, StationNotification
from brasidas.status import Battery
from platformd.app import PlatformDaemon
from platformd.telemetry import TelemetryAggregator
from stationd.client import PlatformConnection
from stationd.daemon import StationDaemon
from stationd.status_view import render

Factory = Callable[..., Awaitable[PlatformDaemon]]


@pytest.fixture
async def station(fleet_key: bytes) -> AsyncIterator[StationDaemon]:
    config = load_config(
        StationConfig,
        None,
        ["station.api_port=0", "station.connect_timeout=2", "telemetry.rate_hz=20"],
    )
    daemon = StationDaemon(config, fleet_key)
    await daemon.start()
    yield daemon
    await daemon.stop()


def aggregator(platform: PlatformDaemon) -> TelemetryAggregator:
    (actor,) = [a for a in platform.supervisor.actors if isinstance(a, TelemetryAggregator)]
    return actor


async def test_station_receives_verified_telemetry_and_refuses_forgeries(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes
) -> None:
    platform = await platform_factory(quiet_platform_config("platform.id=rover-7"), fleet_key)
    notes: list[StationNotification] = []
    station.bus.subscribe(topics.STATION_NOTIFICATIONS, notes.append)
    platform.bus.publish(topics.LIGHTS_STATE, LightsState(main=True, positional=False))

    await station.ctx.connection_manager.ensure("rover-7", platform.ctx.signaling_url)
    api = station.ctx.api
    await wait_until(lambda: _received(station, "rover-7") >= 3)
    report = await api.call_local("get_telemetry", platform_id="rover-7")
    snapshot = report["snapshot"]
    assert report["schema"] == SCHEMA_VERSION
    assert snapshot["override"] == {"mode": "autonomous", "engaged": False, "station": None}
    assert snapshot["lights"] == {"main": True, "positional": False, "errors": {}}
    assert snapshot["computer"]["mem_free_mb"] > 0
    assert len(snapshot["computer"]["load"]) == 3
    assert snapshot["diagnostics"] is None
    assert report["link"]["loss_pct"] == 0.0
    assert report["link"]["rejected_total"] == 0
    assert report["link"]["max_datagram"] < MAX_DATAGRAM
    # get_telemetry_report over signaling carries the same sections.
    connection = station.ctx.connections["rover-7"]
    over_signaling = await connection.call("get_telemetry_report")
    assert set(snapshot) <= set(over_signaling)

    # The platform follows the operator: the next datagrams show the manual override.
    await api.call_local("movrd", platform_id="rover-7", engaged=True)
    await wait_until(lambda: _override(station, "rover-7").engaged)
    assert _override(station, "rover-7") == Override("teleop", True, "station-1")

    # Forged, truncated, garbage and replayed datagrams sent to the station's port.
    link = _link(station, "rover-7")
    assert link.transport is not None
    port = link.transport.get_extra_info("sockname")[1]
    forger = TelemetryEncoder("rover-7", b"\x00" * 32, first_seq=10**9)
    replay_capture = TelemetryDecoder("rover-7", connection.session_key)
    genuine = TelemetryEncoder("rover-7", connection.session_key, first_seq=1)
    autonomous = snapshot_to_wire({Override: Override()})
    old = genuine.encode(autonomous, 0.0)[0]  # authentic but seq 1: a replay
    assert replay_capture.feed(old)
    before = dict(link.decoder.rejected)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.sendto(forger.encode(autonomous, 0.0)[0], ("127.0.0.1", port))
        sock.sendto(b"\x01", ("127.0.0.1", port))
        sock.sendto(bytes((VERSION, 1)) + b"\xc1" * 40, ("127.0.0.1", port))
        sock.sendto(old, ("127.0.0.1", port))
    await wait_until(lambda: sum(link.decoder.rejected.values()) - sum(before.values()) >= 4)
    rejected = link.decoder.rejected
    assert rejected["forged"] - before["forged"] == 2  # bad key; garbage under a bad tag
    assert rejected["truncated"] - before["truncated"] == 1
    assert rejected["replayed"] - before["replayed"] == 1
    assert _override(station, "rover-7").mode == "teleop"  # the real one, not the forger's
    # Still streaming after the attack.
    received = _received(station, "rover-7")
    await wait_until(lambda: _received(station, "rover-7") > received + 2)
    assert not [n for n in notes if n.name == "link_degraded"]

    # Disconnecting ends the stream on the platform.
    await api.call_local("disconnect", platform_id="rover-7")
    await wait_until(lambda: not aggregator(platform).sender.streams)


async def test_station_notices_silence_asks_again_and_the_warning_clears(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    platform = await platform_factory(quiet_platform_config(), fleet_key)
    config = load_config(
        StationConfig,
        None,
        ["station.api_port=0", "telemetry.rate_hz=20", "telemetry.silence_s=0.3"],
    )
    station = StationDaemon(config, fleet_key)
    await station.start()
    try:
        notes: list[StationNotification] = []
        station.bus.subscribe(topics.STATION_NOTIFICATIONS, notes.append)
        await station.ctx.connection_manager.ensure("brasidas-1", platform.ctx.signaling_url)
        await wait_until(lambda: _received(station, "brasidas-1") >= 2)
        agg = aggregator(platform)
        (session_id,) = agg.sender.streams
        # The platform loses the stream (as when its telemetry actor restarts).
        agg.sender.stop_stream(session_id)
        await wait_until(lambda: any(n.name == "link_degraded" and n.active for n in notes))
        report = await station.ctx.api.call_local("get_telemetry", platform_id="brasidas-1")
        assert [w["name"] for w in report["warnings"]] == ["link_degraded"]
        assert report["warnings"][0]["code"] == "90.13"
        assert "telemetry silent" in report["warnings"][0]["message"]
        # After 3 x silence_s the station asks again; the new stream's sequence numbers start
        # above the old ones, so they pass the replay check and the warning clears.
        await wait_until(lambda: any(n.name == "link_degraded" and not n.active for n in notes))
        assert session_id in agg.sender.streams
        link = _link(station, "brasidas-1")
        assert link.decoder.rejected["replayed"] == 0
        assert link.stats.loss_pct == 0.0
        listing = await station.ctx.api.call_local("telemetry_notifications", limit=10)
        assert [(n["name"], n["active"]) for n in listing][-2:] == [
            ("link_degraded", True),
            ("link_degraded", False),
        ]
    finally:
        await station.stop()


async def test_a_failing_section_is_reported_and_the_stream_goes_on(
    station: StationDaemon,
    platform_factory: Factory,
    fleet_key: bytes,
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Defect 5: one section's source raising used to fail the aggregator's task group; the
    actor restarted, every stream was dropped and stations saw seconds of silence."""
    platform = await platform_factory(quiet_platform_config("platform.id=rover-8"), fleet_key)
    platform.bus.publish(topics.LIGHTS_STATE, LightsState(main=True, positional=False))
    await station.ctx.connection_manager.ensure("rover-8", platform.ctx.signaling_url)
    await wait_until(lambda: _received(station, "rover-8") >= 2)
    agg = aggregator(platform)
    (session_id,) = agg.sender.streams
    notes: list[StationNotification] = []
    station.bus.subscribe(topics.STATION_NOTIFICATIONS, notes.append)

    def unreadable(*args: object) -> None:
        raise OSError(5, "Input/output error")

    monkeypatch.setattr("platformd.telemetry.aggregator.system_info", unreadable)
    await wait_until(lambda: _snapshot(station, "rover-8").error(Computer) is not None)
    received = _received(station, "rover-8")
    await wait_until(lambda: _received(station, "rover-8") >= received + 10)

    snapshot = _snapshot(station, "rover-8")
    assert snapshot.error(Computer) == "OSError: [Errno 5] Input/output error"
    assert snapshot.get(Lights) == Lights(True, False)  # the rest goes on
    assert agg.sender.streams.keys() == {session_id}  # the same stream: no restart
    assert platform.supervisor.restarts.get("telemetry", 0) == 0
    assert not [n for n in notes if n.name == "link_degraded"]
    assert platform.ctx.telemetry.errors["computer"] >= 10
    report = await station.ctx.api.call_local("get_telemetry", platform_id="rover-8")
    assert report["snapshot"]["computer"] == {"error": "OSError: [Errno 5] Input/output error"}
    assert "computer   ERROR OSError" in "\n".join(render(report, color=False))

    monkeypatch.undo()  # the source recovers: the section comes back
    await wait_until(lambda: _snapshot(station, "rover-8").get(Computer) is not None)


async def test_request_telemetry_refuses_third_hosts_and_bad_params(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    platform = await platform_factory(quiet_platform_config(), fleet_key)
    connection = PlatformConnection(
        "brasidas-1", platform.ctx.signaling_url, station_id="s", fleet_key=fleet_key
    )
    await connection.open()
    try:
        for params in (
            {"port": 9, "host": "192.0.2.7"},
            {"port": 9, "host": "not-an-ip"},
            {"port": 0},
            {"port": 70000},
            {"port": 9, "rate_hz": 0},
            {"port": 9, "rate_hz": 1000},
        ):
            with pytest.raises(RpcError) as info:
                await connection.call("request_telemetry", **params)
            assert info.value.code == INVALID_PARAMS, params
        answer = await connection.call("request_telemetry", port=9, host="127.0.0.2")
        assert answer["host"] == "127.0.0.2"
        assert answer["auth"] == "hmac-sha256-128"
        assert answer["rate_hz"] == 5.0
        assert connection.capabilities["telemetry"]["push"] is True
        assert await connection.call("stop_telemetry") is True
    finally:
        await connection.close()


async def test_diagnostics_command_adds_the_section_and_health_is_published(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    platform = await platform_factory(quiet_platform_config(), fleet_key)
    connection = PlatformConnection(
        "brasidas-1", platform.ctx.signaling_url, station_id="s", fleet_key=fleet_key
    )
    await connection.open()
    try:
        answer = await connection.call("issue_system_command", group=20, command=0, payload="True")
        assert answer == {"accepted": True, "reason": "", "result": {"diagnostics": True}}
        report = await connection.call("get_telemetry_report")
        assert report["schema"] == SCHEMA_VERSION
        diagnostics = report["diagnostics"]
        assert diagnostics["rpc"]["calls"] >= 2
        assert "actor_restarts" in diagnostics
        answer = await connection.call("issue_system_command", group=20, command=0, payload="x")
        assert answer["accepted"] is False
        await connection.call("issue_system_command", group=20, command=0, payload="OFF")
        assert (await connection.call("get_telemetry_report"))["diagnostics"] is None
    finally:
        await connection.close()
    health = platform.bus.last(topics.PLATFORM_HEALTH)
    assert isinstance(health, PlatformHealth)
    assert health.battery is Battery.UNKNOWN
    assert not health.gps_fix
    assert not health.fault


def _link(station: StationDaemon, platform_id: str):  # type: ignore[no-untyped-def]
    (receiver,) = [a for a in station.supervisor.actors if a.name == "telemetry"]
    return receiver.links[platform_id]  # type: ignore[attr-defined]


def _received(station: StationDaemon, platform_id: str) -> int:
    try:
        return int(_link(station, platform_id).stats.received)
    except KeyError:
        return 0


def _snapshot(station: StationDaemon, platform_id: str) -> Snapshot:
    snapshot: Snapshot = _link(station, platform_id).snapshot
    return snapshot


def _override(station: StationDaemon, platform_id: str) -> Override:
    return _snapshot(station, platform_id).get(Override) or Override()


async def test_a_silent_sessions_stream_pauses_and_resumes_with_its_next_call(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    # Heartbeats every 0.1 s: a session silent for 3 of them (but never less than hold_after,
    # 0.3 s) has lost its link; its session itself lasts (session_timeout 60 s).
    daemon = await platform_factory(
        quiet_platform_config(
            "signaling.heartbeat_interval=0.1",
            "signaling.session_timeout=60",
            "failsafe.hold_after=0.3",
        ),
        fleet_key,
    )
    connection = PlatformConnection(
        daemon.config.platform.id, daemon.ctx.signaling_url, station_id="st", fleet_key=fleet_key
    )
    await connection.open()
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        sock.setblocking(False)

        def drain() -> int:
            count = 0
            while True:
                try:
                    sock.recv(MAX_DATAGRAM)
                except BlockingIOError:
                    return count
                count += 1

        try:
            await connection.call("request_telemetry", port=sock.getsockname()[1], rate_hz=20)
            received = 0

            def heard() -> bool:
                nonlocal received
                received += drain()
                return received >= 3

            await wait_until(heard)
            # The station's heartbeats stop (its link is cut): the stream pauses.
            assert connection._heartbeat is not None
            connection._heartbeat.cancel()
            session = daemon.ctx.sessions.sessions[connection.session_id]
            await wait_until(lambda: not _live(daemon, session.session_id))
            drain()
            paused = _paused(daemon)
            await wait_until(lambda: _paused(daemon) >= paused + 5)
            assert drain() == 0
            assert connection.session_id in daemon.ctx.sessions.sessions
            # A call (the link is back): the same stream resumes by itself.
            await connection.call("heartbeat")
            received = 0
            await wait_until(heard)
        finally:
            await connection.close()


def _live(daemon: PlatformDaemon, session_id: str) -> bool:
    return bool(_aggregator(daemon).session_live(session_id))


def _paused(daemon: PlatformDaemon) -> int:
    return _aggregator(daemon).sender.counters["paused_snapshots"]


def _aggregator(daemon: PlatformDaemon) -> TelemetryAggregator:
    found = [a for a in daemon.ctx.supervisor.actors if isinstance(a, TelemetryAggregator)]
    assert len(found) == 1
    return found[0]
