"""Issue 26, defect 6: beacons from an earlier boot are refused. The platform's boot number is
kept on disk and only grows; a station takes a lower one only after the platform announced it,
signed for that station's connection."""

from __future__ import annotations

import asyncio
import socket
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

from conftest import free_udp_port, quiet_platform_config, running_station
from support.beacon import beacon_config, sample

from brasidas.codecs import beacon as codec
from brasidas.codecs.beacon import DropReason
from brasidas.discovery import PlatformDirectory
from brasidas.status import StatusWord
from platformd.app import PlatformDaemon
from platformd.boot_counter import boot_counter_path, next_boot
from stationd.client import PlatformConnection, _announced_boot

Factory = Callable[..., Awaitable[PlatformDaemon]]


def test_beacons_of_an_earlier_boot_are_refused_even_interleaved(fleet_key: bytes) -> None:
    directory = PlatformDirectory(fleet_key)
    old, new = 1_790_000_000, 1_790_000_500
    directory.receive(codec.encode(sample(boot=new, seq=1), fleet_key), "192.0.2.5")
    for seq in (7, 8, 9):  # the previous boot's beacons, replayed between the live ones
        assert (
            directory.receive(codec.encode(sample(boot=old, seq=seq), fleet_key), "10.6.6.6")
            is None
        )
        live = codec.encode(sample(boot=new, seq=seq), fleet_key)
        entry, _ = directory.receive(live, "192.0.2.5") or (None, False)
        assert entry is not None
        assert entry.address == "192.0.2.5"
    assert directory.dropped[DropReason.REPLAY.value] == 3


def test_a_lower_boot_is_taken_only_once_announced(fleet_key: bytes) -> None:
    directory = PlatformDirectory(fleet_key)
    platform_id = sample().platform_id
    directory.receive(codec.encode(sample(boot=5000, seq=3), fleet_key), "192.0.2.5")
    reset = codec.encode(sample(boot=12, seq=1), fleet_key)  # its state folder was lost
    assert directory.receive(reset, "192.0.2.5") is None
    directory.announce_boot(platform_id, 12)
    assert directory.receive(reset, "192.0.2.5") is not None
    # Earlier than the announced boot: still refused.
    earlier = codec.encode(sample(boot=11, seq=99), fleet_key)
    assert directory.receive(earlier, "10.6.6.6") is None


def test_the_announcement_is_signed_for_one_connection(fleet_key: bytes) -> None:
    proof = codec.boot_proof(fleet_key, "rover-1", 12, "nonce-a")
    answer = {"boot": 12, "boot_proof": proof}
    assert _announced_boot(answer, fleet_key, "rover-1", "nonce-a") == 12
    assert _announced_boot(answer, fleet_key, "rover-1", "nonce-b") is None  # replayed
    assert _announced_boot(answer, fleet_key, "rover-2", "nonce-a") is None
    assert _announced_boot({**answer, "boot": 13}, fleet_key, "rover-1", "nonce-a") is None
    forged = {"boot": 12, "boot_proof": codec.boot_proof(bytes(32), "rover-1", 12, "nonce-a")}
    assert _announced_boot(forged, fleet_key, "rover-1", "nonce-a") is None


def test_the_boot_counter_only_grows_and_is_kept(tmp_path: Path) -> None:
    path = tmp_path / "boot-counter"
    first = next_boot(path, 1_790_000_000.0)
    assert first == 1_790_000_000
    assert next_boot(path, 1_790_000_000.0) == first + 1
    assert next_boot(path, 0.0) == first + 2  # the clock at 1970 (no RTC): still grows
    assert int(path.read_text()) == first + 2
    path.write_text("garbage")
    assert next_boot(path, 1_790_000_100.0) == 1_790_000_100  # damaged: from the clock


async def test_a_restarted_platform_announces_a_higher_boot_to_its_station(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    config = quiet_platform_config(*beacon_config(free_udp_port()))
    platform = await platform_factory(config, fleet_key)
    first = platform.ctx.boot
    assert first > 0
    assert int(boot_counter_path().read_text()) == first
    await platform.stop()
    platform = await platform_factory(config, fleet_key)
    assert platform.ctx.boot > first
    connection = PlatformConnection(
        config.platform.id, platform.ctx.signaling_url, station_id="op", fleet_key=fleet_key
    )
    await connection.open()
    try:
        assert connection.boot == platform.ctx.boot
    finally:
        await connection.close()


async def test_a_station_takes_a_lower_boot_after_the_platforms_signed_announcement(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    port = free_udp_port()
    config = quiet_platform_config(
        *beacon_config(port, "beacon.min_interval=0.1", "beacon.max_interval=0.3")
    )
    platform = await platform_factory(config, fleet_key)
    platform_id = config.platform.id
    async with running_station(fleet_key, f"discovery.port={port}") as station:
        api = station.ctx.api

        async def stats() -> dict[str, Any]:
            return dict(await api.call_local("discovery_stats"))

        await wait_until_async(lambda s: s["accepted"] >= 1, stats)
        # A higher boot was seen once (before the platform's counter was reset): the live
        # beacons of the platform's real, lower boot are refused as replays ...
        higher = codec.Beacon(
            platform_id, platform.ctx.signaling_url, StatusWord(), platform.ctx.boot + 1000, 1
        )
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
            sock.sendto(codec.encode(higher, fleet_key), ("127.0.0.1", port))
        await wait_until_async(lambda s: s["dropped"]["replay"] >= 2, stats)
        # ... until the platform announces its boot over the session the station opens.
        await api.call_local("connect", platform_id=platform_id, url=platform.ctx.signaling_url)
        accepted = (await stats())["accepted"]
        await wait_until_async(lambda s: s["accepted"] >= accepted + 2, stats)


async def wait_until_async(
    condition: Callable[[dict[str, Any]], bool],
    read: Callable[[], Awaitable[dict[str, Any]]],
    timeout: float = 10.0,
) -> None:
    async with asyncio.timeout(timeout):
        while not condition(await read()):
            await asyncio.sleep(0.05)
