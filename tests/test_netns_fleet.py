"""A fleet of 20 platforms (discovery only, one process) and 3 stations on the test network:
every station lists all 20 and drops a dead one within the 4 s expiry (R-9.3)."""

from __future__ import annotations

import socket
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from netns import API_PORT, Fleet, network_fixture, requires_netns, wait_for

from brasidas.netem.beacons import BeaconFleet
from brasidas.netem.netns import BROADCAST, TestNetwork, socket_in

pytestmark = requires_netns
network = network_fixture("fleet")
COUNT = 20


@pytest.fixture(scope="module")
def fleet(network: TestNetwork, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet]:
    fleet = Fleet(network, Path(tmp_path_factory.mktemp("fleet")))
    for n in (1, 2, 3):
        fleet.station(network.add_host(f"st{n}"), f"station-{n}")
    yield fleet
    fleet.stop()


async def test_three_stations_list_twenty_platforms_and_drop_a_dead_one(
    fleet: Fleet, network: TestNetwork
) -> None:
    host = network.add_host("fleet", extra_addresses=COUNT - 1)
    addresses = [host.address, *network.addresses_of(host, COUNT - 1)]
    ids = [f"ugv-{n:02d}" for n in range(COUNT)]
    beacons = BeaconFleet(
        ids,
        addresses,
        fleet.key,
        BROADCAST,
        21000,
        interval=1.0,
        socket_factory=lambda: socket_in(host.namespace, socket.AF_INET, socket.SOCK_DGRAM),
    )
    stations = list(fleet.daemons)
    for station in stations:
        await fleet.wait_listening(station, "127.0.0.1", API_PORT)
    beacons.start()
    try:
        started = time.monotonic()

        async def all_listed() -> bool:
            for station in stations:
                entries = await fleet.api(station, "list_platforms")
                if sorted(e["id"] for e in entries) != ids:
                    return False
            return True

        await wait_for(all_listed, 10, step=0.1)
        full = time.monotonic() - started
        last_beacon = beacons.silence("ugv-07")
        dropped_after: dict[str, float] = {}

        async def all_dropped() -> bool:
            for station in stations:
                if station.name in dropped_after:
                    continue
                entries = await fleet.api(station, "list_platforms")
                listed = {e["id"] for e in entries}
                if "ugv-07" not in listed:
                    assert listed == set(ids) - {"ugv-07"}
                    dropped_after[station.name] = time.monotonic() - last_beacon
            return len(dropped_after) == len(stations)

        await wait_for(all_dropped, 10, step=0.05)
        stats = await fleet.api(stations[0], "discovery_stats")
    finally:
        beacons.close()
    print(
        f"\n{COUNT} platforms listed by all 3 stations {full:.1f} s after the first beacon; "
        f"ugv-07 dropped {', '.join(f'{k} {v:.2f} s' for k, v in sorted(dropped_after.items()))} "
        f"after its last beacon; beacons sent {beacons.sent} "
        f"({beacons.bytes_sent / max(1, beacons.sent):.0f} bytes each); station-1: {stats}"
    )
    # Expiry 4 s after the last beacon, checked every 0.5 s, plus this test's polling.
    assert max(dropped_after.values()) < 4.0 + 0.5 + 0.5
    assert min(dropped_after.values()) > 3.9
    assert sum(stats["dropped"].values()) == 0
