"""A lost session comes back by itself, without the override (issue 14 follow-up): a station
daemon driving a platform over real sockets; the platform goes away and comes back on the same
address. The station re-establishes its session as soon as the platform answers, as an
observer: nothing moves until the operator re-engages. A station back on a new session takes
its own control back without ``--force``; another station still cannot."""

from __future__ import annotations

from collections.abc import Awaitable, Callable

import pytest
from conftest import free_tcp_port, quiet_platform_config, running_station, wait_until

from brasidas import topics
from brasidas.codecs.jsonrpc import RpcError
from brasidas.messages import Velocity
from platformd.app import PlatformDaemon
from stationd.client import PlatformConnection

Factory = Callable[..., Awaitable[PlatformDaemon]]


async def test_the_station_reconnects_by_itself_and_never_re_engages(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    port = free_tcp_port()
    config = quiet_platform_config(f"signaling.port={port}", "signaling.heartbeat_interval=0.2")
    first = await platform_factory(config, fleet_key)
    platform_id, url = first.config.platform.id, first.ctx.signaling_url
    async with running_station(fleet_key, "station.id=alpha", "station.connect_timeout=1") as st:
        api = st.ctx.api
        await api.call_local("connect", platform_id=platform_id, url=url)
        assert (await api.call_local("movrd", platform_id=platform_id, engaged=True))["accepted"]
        await wait_until(lambda: st.ctx.teleop is not None and platform_id in st.ctx.teleop.senders)
        await api.call_local("teleop_set", platform_id=platform_id, linear=0.5, angular=0.0)
        await wait_until(lambda: (first.bus.last(topics.MOTION_STATE) or _idle).command.linear > 0)
        old = st.ctx.connections[platform_id]

        # The platform goes away (a long cut, a reboot): the session is lost.
        await first.stop()
        await wait_until(lambda: old.closed.is_set())
        # It comes back on the same address: the station reconnects without being asked.
        second = await platform_factory(config, fleet_key)
        await wait_until(
            lambda: (
                (c := st.ctx.connections.get(platform_id)) is not None
                and c is not old
                and not c.closed.is_set()
            ),
            timeout=15,
        )
        new = st.ctx.connections[platform_id]
        await wait_until(lambda: platform_id in st.ctx.teleop.senders)  # type: ignore[union-attr]
        status = await api.call_local("teleop_status", platform_id=platform_id)
        assert status["engaged"] is False
        assert status["streaming"] is False
        # Nothing moves: no override, not one $PVEL accepted, even with a drive input alive.
        await api.call_local("teleop_set", platform_id=platform_id, linear=0.5, angular=0.0)
        await new.heartbeat()
        override = second.bus.last(topics.OVERRIDE_STATE)
        assert override is not None
        assert not override.engaged
        assert second.ctx.authority.station_id is None
        assert not new.manual_override
        # The operator re-engages deliberately: it drives again.
        assert (await api.call_local("movrd", platform_id=platform_id, engaged=True))["accepted"]
        await api.call_local("teleop_set", platform_id=platform_id, linear=0.5, angular=0.0)
        await wait_until(lambda: (second.bus.last(topics.MOTION_STATE) or _idle).command.linear > 0)


class _Idle:
    command = Velocity(0.0, 0.0)


_idle = _Idle()


async def test_a_station_back_on_a_new_session_takes_its_control_back_another_cannot(
    platform_factory: Factory, fleet_key: bytes, caplog: pytest.LogCaptureFixture
) -> None:
    daemon = await platform_factory(
        quiet_platform_config(
            "signaling.heartbeat_interval=60",
            "signaling.session_timeout=60",
            "failsafe.hold_after=0.3",
            "failsafe.action=hold",
        ),
        fleet_key,
    )

    def connection(name: str) -> PlatformConnection:
        return PlatformConnection(
            daemon.config.platform.id,
            daemon.ctx.signaling_url,
            station_id=name,
            fleet_key=fleet_key,
        )

    lost, back, other = connection("alpha"), connection("alpha"), connection("bravo")
    try:
        await lost.open()
        assert await lost.call("set_manual_override", engaged=True) is True
        # alpha's link goes silent: the ladder holds (its session stays, action = hold).
        await wait_until(
            lambda: (
                (s := daemon.bus.last(topics.FAILSAFE_STATE)) is not None and s.step.value == "hold"
            )
        )
        overrides: list[bool] = []
        daemon.bus.subscribe(topics.OVERRIDE_STATE, lambda state: overrides.append(state.engaged))
        # Its WebSocket's close arrives when the link returns: the ladder still decides (with
        # action = hold the robot keeps holding; the session is not ended by it).
        await lost._client.close()
        await wait_until(lambda: "override holder lost while the failsafe holds" in caplog.text)
        assert lost.session_id in daemon.ctx.sessions.sessions
        await back.open()
        await other.open()
        with pytest.raises(RpcError, match="control held by station alpha"):
            await other.call("set_manual_override", engaged=True)
        assert daemon.ctx.authority.station_id == "alpha"
        # alpha on its new session re-engages, no --force needed: its old override goes.
        assert await back.call("set_manual_override", engaged=True) is True
        override = daemon.bus.last(topics.OVERRIDE_STATE)
        assert override is not None
        assert override.engaged
        assert override.session_id == back.session_id
        assert daemon.ctx.authority.counters["reclaims"] == 1
        # The override went from the old session to the new one; never to Autonomous Mode
        # meanwhile but for the instant of the handover inside the reclaim itself.
        assert overrides[-2:] == [False, True]
        assert overrides.count(False) == 1
        failsafe = daemon.bus.last(topics.FAILSAFE_STATE)
        assert failsafe is not None
        assert failsafe.step.value == "normal"
    finally:
        for conn in (lost, back, other):
            await conn.close()
