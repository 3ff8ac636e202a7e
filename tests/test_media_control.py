"""Stream control among stations (issue 19, items 4 and 5) on loopback: pausing and resuming
are control, an observer's start adds its own copy only; destinations a session may choose.
The same on a hostile mesh of namespaces: tests/test_netns_hostile.py."""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Awaitable, Callable, Iterator

import pytest
from conftest import quiet_platform_config, wait_until

from brasidas.config import PlatformConfig, load_config
from brasidas.config.loader import ConfigError
from platformd.app import PlatformDaemon
from platformd.media import in_destinations
from platformd.session_table import Session
from stationd.client import PlatformConnection

Factory = Callable[..., Awaitable[PlatformDaemon]]


@pytest.fixture
def video_socket() -> Iterator[socket.socket]:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    sock.setblocking(False)
    yield sock
    sock.close()


def drain(sock: socket.socket) -> int:
    count = 0
    while True:
        try:
            sock.recv(65536)
        except BlockingIOError:
            return count
        count += 1


async def received_in(sock: socket.socket, seconds: float) -> int:
    drain(sock)
    await asyncio.sleep(seconds)
    return drain(sock)


async def station(daemon: PlatformDaemon, key: bytes, name: str) -> PlatformConnection:
    conn = PlatformConnection(
        daemon.config.platform.id, daemon.ctx.signaling_url, station_id=name, fleet_key=key
    )
    await conn.open()
    return conn


async def test_only_control_resumes_a_paused_stream(
    platform_factory: Factory, fleet_key: bytes, video_socket: socket.socket
) -> None:
    daemon = await platform_factory(
        quiet_platform_config(
            "sim.enabled=true", "navcam.enabled=true", "navcam.width=160", "navcam.height=120"
        ),
        fleet_key,
    )
    holder = await station(daemon, fleet_key, "holder")
    observer = await station(daemon, fleet_key, "observer")
    port = video_socket.getsockname()[1]
    try:
        await holder.call("start_stream", name="navcam", port=port)
        await wait_until(lambda: drain(video_socket) > 0, timeout=15)
        assert (await holder.call("pause_stream", name="navcam"))["state"] == "paused"
        await received_in(video_socket, 0.3)  # what was on its way
        # The observer's start, by the method and by 10.1: its own copy joins, paused.
        started = await observer.call("start_stream", name="navcam")
        assert started["state"] == "paused"
        answer = await observer.call("issue_system_command", group=10, command=1, payload="")
        assert answer["accepted"]
        assert answer["result"] == {"navcam": "paused"}
        assert await received_in(video_socket, 1.5) == 0
        assert "navcam" in daemon.ctx.media.paused  # type: ignore[union-attr]
        # The holder resumes.
        assert (await holder.call("start_stream", name="navcam", port=port))["state"] == "playing"
        await wait_until(lambda: drain(video_socket) > 0, timeout=15)
    finally:
        await observer.close()
        await holder.close()


def test_configured_destinations_are_addresses_or_networks() -> None:
    config = load_config(
        PlatformConfig, None, ['security.stream_destinations=["198.51.100.7", "239.1.0.0/16"]']
    )
    allowed = config.security.stream_destinations
    assert in_destinations("198.51.100.7", allowed)
    assert in_destinations("239.1.2.3", allowed)
    assert not in_destinations("198.51.100.8", allowed)
    assert not in_destinations("rover.local", allowed)
    with pytest.raises(ConfigError, match="security.stream_destinations"):
        load_config(PlatformConfig, None, ['security.stream_destinations=["not an address"]'])


async def test_a_session_gets_its_own_address_or_loopback_only(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(
        quiet_platform_config(
            "sim.enabled=true",
            "navcam.enabled=true",
            'security.stream_destinations=["192.0.2.0/24"]',
        ),
        fleet_key,
    )
    media = daemon.ctx.media
    assert media is not None
    peer = Session("s", "st", "198.51.100.3", None, 0.0, 0.0)
    refused = "caller's own address (198.51.100.3)"
    # Allowed by policy (whether this machine routes them is its own business).
    for own in ("198.51.100.3", "127.0.0.1", "::1", "192.0.2.9"):
        assert refused not in str(media.destination_refusal(own, peer)), own
    for other in ("198.51.100.2", "224.0.0.1", "198.18.0.4", "rover.local"):
        assert refused in str(media.destination_refusal(other, peer)), other
    assert media.destination_refusal("127.0.0.1", peer) is None
    assert media.destination_refusal("198.18.0.4", None) is None  # the platform itself
