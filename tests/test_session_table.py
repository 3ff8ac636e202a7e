"""The session port (platformd.session_table): every session is announced opened before it is
announced closed, once each, whoever opens it (a station's connect, a MAVLink ground station).
No sockets: tables, a bus and the MAVLink service's own session bookkeeping."""

from __future__ import annotations

import pytest
from conftest import quiet_platform_config

from brasidas import topics
from brasidas.actor import Supervisor
from brasidas.bus import Bus
from brasidas.codecs.jsonrpc import Dispatcher
from brasidas.messages import SessionClosed, SessionOpened
from platformd.context import PlatformContext
from platformd.mavlink.model import SetMode
from platformd.mavlink.modes import FlightMode
from platformd.mavlink.service import MavlinkService
from platformd.session_table import Session, SessionAlreadyOpen, SessionTable

Event = SessionOpened | SessionClosed


def session(session_id: str = "token-1", station_id: str = "station-a") -> Session:
    return Session(session_id, station_id, "192.0.2.5", None, 10.0, 10.0)


def table_with_log() -> tuple[SessionTable, list[Event]]:
    log: list[Event] = []
    return SessionTable(announce=log.append), log


def test_an_opened_session_is_announced_then_its_close_with_the_reason() -> None:
    table, log = table_with_log()
    opened = session()
    table.open(opened)
    assert table.get("token-1") is opened
    assert table.close("token-1", "disconnect") is opened
    assert table.get("token-1") is None
    assert log == [
        SessionOpened("token-1", "station-a", "192.0.2.5"),
        SessionClosed("token-1", "station-a", "disconnect"),
    ]


def test_a_session_never_opened_is_never_announced_closed() -> None:
    table, log = table_with_log()
    assert table.close("never-opened", "timeout") is None
    assert log == []


def test_a_second_close_announces_nothing() -> None:
    table, log = table_with_log()
    table.open(session())
    table.close("token-1", "timeout")
    assert table.close("token-1", "shutdown") is None
    assert [type(event) for event in log] == [SessionOpened, SessionClosed]


def test_an_open_id_is_not_opened_again_and_its_first_opening_stands() -> None:
    table, log = table_with_log()
    first = session(station_id="station-a")
    table.open(first)
    with pytest.raises(SessionAlreadyOpen):
        table.open(session(station_id="station-b"))
    assert table.get("token-1") is first
    assert log == [SessionOpened("token-1", "station-a", "192.0.2.5")]


def platform_context(*overrides: str) -> PlatformContext:
    return PlatformContext(
        config=quiet_platform_config(*overrides),
        bus=Bus(),
        supervisor=Supervisor(),
        rpc=Dispatcher(),
        fleet_key=None,
    )


def bus_log(ctx: PlatformContext) -> list[Event]:
    log: list[Event] = []
    ctx.bus.subscribe(topics.SESSION_OPENED, log.append)
    ctx.bus.subscribe(topics.SESSION_CLOSED, log.append)
    return log


def test_the_platforms_table_announces_on_the_bus() -> None:
    ctx = platform_context()
    log = bus_log(ctx)
    ctx.sessions.open(session())
    ctx.sessions.close("token-1", "timeout")
    assert log == [
        SessionOpened("token-1", "station-a", "192.0.2.5"),
        SessionClosed("token-1", "station-a", "timeout"),
    ]


def test_a_ground_stations_session_opens_announced_before_it_closes() -> None:
    ctx = platform_context("mavlink.enabled=true")
    log = bus_log(ctx)
    service = MavlinkService(ctx, None)  # not bound: only its session bookkeeping is used
    request = SetMode(("192.0.2.9", 14550), 250, 190, False, FlightMode.HOLD, 176)
    gcs = service.session_for(request)
    assert service.session_for(request) is gcs  # one session per ground station
    assert ctx.sessions.get(gcs.session_id) is gcs
    # Ended by the platform (a timeout): the service forgets it, the next request reopens.
    ctx.sessions.close(gcs.session_id, "timeout")
    again = service.session_for(request)
    assert again is not gcs
    service.close()
    service.close()  # idempotent: nothing announced twice
    assert [(type(event).__name__, event.station_id) for event in log] == [
        ("SessionOpened", "gcs250@192.0.2.9:14550"),
        ("SessionClosed", "gcs250@192.0.2.9:14550"),
        ("SessionOpened", "gcs250@192.0.2.9:14550"),
        ("SessionClosed", "gcs250@192.0.2.9:14550"),
    ]
    timed_out, stopped = log[1], log[3]
    assert isinstance(timed_out, SessionClosed)
    assert timed_out.reason == "timeout"
    assert isinstance(stopped, SessionClosed)
    assert stopped.reason == "MAVLink endpoint stopped"
    assert ctx.sessions.get(again.session_id) is None
