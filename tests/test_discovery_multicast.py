"""Multicast beacons (R-0.6.1) on loopback, and each platform's own list of the others (R-9)."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable

from conftest import free_udp_port, quiet_platform_config, wait_until

from brasidas import security
from brasidas.codecs.telemetry_schema import Platforms
from brasidas.config import StationConfig, load_config
from platformd.app import PlatformDaemon
from stationd.discovery import discover

Factory = Callable[..., Awaitable[PlatformDaemon]]
GROUP = "239.255.21.7"


def _multicast_platform(port: int, platform_id: str) -> list[str]:
    return [
        "beacon.enabled=true",
        f"beacon.port={port}",
        f'beacon.destinations=["{GROUP}"]',  # sent via beacon.interface_host (127.0.0.1)
        "beacon.max_interval=0.7",
        f"platform.id={platform_id}",
    ]


async def test_list_hears_a_multicast_beacon_only_after_joining_the_group(
    platform_factory: Factory,
) -> None:
    port = free_udp_port()
    key = security.generate_key(security.default_key_path())
    platform = await platform_factory(quiet_platform_config(*_multicast_platform(port, "m-1")), key)

    def config(*extra: str) -> StationConfig:
        return load_config(StationConfig, None, [f"discovery.port={port}", *extra])

    joined, deaf = await asyncio.gather(
        discover(config(f'discovery.groups=["{GROUP}"]'), key, 1.6),
        discover(config(), key, 1.6),
    )
    assert [e["id"] for e in joined] == ["m-1"]
    assert joined[0]["url"] == platform.ctx.signaling_url
    assert deaf == []  # not in the group: nothing heard


async def test_platforms_list_each_other_but_not_themselves(platform_factory: Factory) -> None:
    port = free_udp_port()
    key = security.generate_key(security.default_key_path())
    one = await platform_factory(quiet_platform_config(*_multicast_platform(port, "m-1")), key)
    two = await platform_factory(quiet_platform_config(*_multicast_platform(port, "m-2")), key)

    async def ids(platform: PlatformDaemon) -> list[object]:
        entries = await platform.ctx.rpc.call_local("list_platforms")
        return [entry["id"] for entry in entries]

    async def both_listed() -> bool:
        return await ids(one) == ["m-2"] and await ids(two) == ["m-1"]

    for _ in range(100):
        if await both_listed():
            break
        await asyncio.sleep(0.05)
    assert await ids(one) == ["m-2"]
    assert await ids(two) == ["m-1"]
    # The same list rides in telemetry.
    section = one.ctx.telemetry.build_one(Platforms)
    assert isinstance(section, Platforms)
    assert list(section.age_s) == ["m-2"]
    # One stops: the other drops it after the expiry (4 s).
    await two.stop()
    await wait_until(lambda: one.ctx.telemetry.build_one(Platforms) == Platforms({}), timeout=8)
