"""Advertisement and discovery: the beacon codec, the platform's advertiser, the station's list."""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import os
import socket
from collections.abc import AsyncIterator, Awaitable, Callable

import msgpack
import pytest
from conftest import free_udp_port, quiet_platform_config, wait_until
from hypothesis import given, settings
from hypothesis import strategies as st
from support.beacon import beacon_config, sample

from brasidas import security, topics
from brasidas.codecs import beacon as codec
from brasidas.codecs.beacon import Beacon, BeaconError, DropReason, ReplayGuard
from brasidas.config import StationConfig, load_config
from brasidas.discovery import PlatformDirectory
from brasidas.messages import Position
from brasidas.status import Battery, StatusWord
from platformd.app import PlatformDaemon
from platformd.beacon import distance_m
from stationd import cli
from stationd.client import PlatformConnection
from stationd.daemon import StationDaemon

Factory = Callable[..., Awaitable[PlatformDaemon]]
KEY = bytes(range(32))


# ------------------------------------------------------------------ codec


def test_round_trip_under_100_bytes_signature_included() -> None:
    beacon = sample()
    datagram = codec.encode(beacon, KEY)
    assert len(datagram) < 100
    decoded = codec.decode(datagram, KEY)
    assert decoded.platform_id == beacon.platform_id
    assert decoded.signaling_url == beacon.signaling_url
    assert decoded.status == beacon.status
    assert (decoded.boot, decoded.seq) == (beacon.boot, beacon.seq)
    assert decoded.position is not None
    assert decoded.position == pytest.approx(beacon.position, abs=1e-7)


def test_position_is_optional() -> None:
    assert codec.decode(codec.encode(sample(position=None), KEY), KEY).position is None


def test_an_over_long_identity_is_refused_at_encoding() -> None:
    with pytest.raises(ValueError, match="limit 100"):
        codec.encode(sample(platform_id="x" * 80), KEY)


def test_forged_unsigned_and_foreign_beacons_are_refused() -> None:
    datagram = codec.encode(sample(), KEY)
    with pytest.raises(BeaconError) as forged:
        codec.decode(datagram[:-1] + bytes([datagram[-1] ^ 1]), KEY)
    assert forged.value.reason is DropReason.BAD_TAG
    with pytest.raises(BeaconError) as unsigned:
        codec.decode(codec.encode(sample(), None), KEY)
    assert unsigned.value.reason is DropReason.UNSIGNED
    with pytest.raises(BeaconError) as other_fleet:
        codec.decode(codec.encode(sample(), os.urandom(32)), KEY)
    assert other_fleet.value.reason is DropReason.BAD_TAG
    # A tampered body fails the tag too (here: the status word).
    body = msgpack.packb([1, "brasidas-rover-12", "http://10.144.23.117:8765", 1, 1, 1, None, None])
    with pytest.raises(BeaconError) as tampered:
        codec.decode(body + datagram[-codec.TAG_LENGTH :], KEY)
    assert tampered.value.reason is DropReason.BAD_TAG


def test_an_insecure_station_accepts_unsigned_beacons() -> None:
    assert codec.decode(codec.encode(sample(), None), None).platform_id == "brasidas-rover-12"


def test_replays_are_refused_and_a_new_boot_is_accepted() -> None:
    guard = ReplayGuard()
    guard.check(sample(seq=5))
    for seq in (5, 4):
        with pytest.raises(BeaconError) as replay:
            guard.check(sample(seq=seq))
        assert replay.value.reason is DropReason.REPLAY
    guard.check(sample(seq=6))
    guard.check(sample(boot=0xDEADBEEF + 1, seq=1))  # the platform restarted: boots grow


@pytest.mark.parametrize(
    "fields",
    [
        [2, "a", "b", 0, 0, 0, None, None],  # unknown version
        [1, "a", "b", 0, 0, 0, None],  # short
        [1, "", "b", 0, 0, 0, None, None],  # empty id
        [1, "a", "b", -1, 0, 0, None, None],  # negative status
        [1, "a", "b", 0, 0, 2**32, None, None],  # seq too large
        [1, "a", "b", 0, 0, 0, 950_000_000, 0],  # latitude out of range
        [1, "a", "b", 0, 0, 0, 1.5, 2.5],  # floats instead of 1e-7 degrees
        {"id": "a"},
    ],
)
def test_malformed_beacons_are_refused(fields: object) -> None:
    with pytest.raises(BeaconError) as err:
        codec.decode(msgpack.packb(fields), None)
    assert err.value.reason in (DropReason.MALFORMED, DropReason.VERSION)


@given(st.binary(max_size=200))
def test_garbage_never_raises_anything_but_beacon_error(data: bytes) -> None:
    for key in (KEY, None):
        with contextlib.suppress(BeaconError):
            codec.decode(data, key)


@given(
    st.text(min_size=1, max_size=20),
    st.integers(0, 2**11 - 1),
    st.integers(0, 2**32 - 1),
    st.one_of(
        st.none(),
        st.tuples(st.floats(-90, 90), st.floats(-180, 180)),
    ),
)
def test_round_trip_property(
    platform_id: str, word: int, seq: int, position: tuple[float, float] | None
) -> None:
    beacon = sample(
        platform_id=platform_id,
        status=StatusWord.decode(word),
        seq=seq,
        position=position,
        signaling_url="http://127.0.0.1:8765",
    )
    try:
        datagram = codec.encode(beacon, KEY)
    except ValueError:
        assert len(platform_id.encode()) > 20  # only a long multi-byte id can overflow
        return
    decoded = codec.decode(datagram, KEY)
    assert decoded.status.encode() == word
    assert decoded.seq == seq
    if position is None:
        assert decoded.position is None
    else:
        assert decoded.position == pytest.approx(position, abs=1e-7)


def test_distance_at_the_metre_scale() -> None:
    # 1e-5 degree of latitude is about 1.11 m anywhere.
    assert distance_m((37.0, 23.0), (37.00001, 23.0)) == pytest.approx(1.112, abs=0.01)


# ------------------------------------------------------------------ directory (fake clock)


class FakeClock:
    def __init__(self) -> None:
        self.now = 50.0

    def __call__(self) -> float:
        return self.now


def test_directory_stamps_with_its_own_clock_and_expires_after_4_s() -> None:
    clock = FakeClock()
    directory = PlatformDirectory(KEY, 4.0, clock=clock, wall_clock=lambda: 1.7e9)
    assert directory.receive(codec.encode(sample(seq=1), KEY), "10.0.0.5") is not None
    clock.now += 3.9
    assert directory.receive(codec.encode(sample(seq=2), KEY), "10.0.0.5") is not None
    clock.now += 3.9
    [entry] = directory.entries()
    assert entry["id"] == "brasidas-rover-12"
    assert entry["address"] == "10.0.0.5"
    assert entry["age_s"] == pytest.approx(3.9)
    assert entry["beacons"] == 2
    assert entry["status"]["movrd"] is True
    assert entry["status"]["battery"] == "medium"
    clock.now += 0.2
    assert directory.entries() == []


def test_directory_counts_what_it_drops() -> None:
    directory = PlatformDirectory(KEY, 4.0)
    good = codec.encode(sample(seq=1), KEY)
    for datagram in (b"\xff\x00garbage", codec.encode(sample(seq=2), None), good, good):
        directory.receive(datagram, "127.0.0.1")
    stats = directory.stats()
    assert stats["accepted"] == 1
    assert stats["received"] == 4
    assert stats["dropped"]["malformed"] == 1
    assert stats["dropped"]["unsigned"] == 1
    assert stats["dropped"]["replay"] == 1


# ------------------------------------------------------------------ advertiser on real sockets


class Collector(asyncio.DatagramProtocol):
    """Decodes every beacon with the fleet key, stamped with the loop's clock."""

    def __init__(self, key: bytes) -> None:
        self.key = key
        self.beacons: asyncio.Queue[tuple[float, Beacon]] = asyncio.Queue()

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.beacons.put_nowait((asyncio.get_running_loop().time(), codec.decode(data, self.key)))


@pytest.fixture
async def collector(fleet_key: bytes) -> AsyncIterator[tuple[int, Collector]]:
    port = free_udp_port()
    transport, protocol = await asyncio.get_running_loop().create_datagram_endpoint(
        lambda: Collector(fleet_key), local_addr=("127.0.0.1", port)
    )
    yield port, protocol
    transport.close()


async def test_platform_beacons_at_start_and_at_most_every_3_s(
    platform_factory: Factory, fleet_key: bytes, collector: tuple[int, Collector]
) -> None:
    port, protocol = collector
    config = quiet_platform_config(*beacon_config(port, "beacon.max_interval=1.0"))
    platform = await platform_factory(config, fleet_key)
    t0, first = await asyncio.wait_for(protocol.beacons.get(), 5)
    assert first.platform_id == config.platform.id
    assert first.signaling_url == platform.ctx.signaling_url
    assert first.position is None
    assert first.status.movrd is False
    t1, second = await asyncio.wait_for(protocol.beacons.get(), 5)
    assert second.seq == first.seq + 1
    assert second.boot == first.boot
    assert t1 - t0 >= 0.55  # the 0.6 s floor, less timer slack


async def test_a_status_change_or_a_move_beacons_at_once_but_not_faster_than_0_6_s(
    platform_factory: Factory, fleet_key: bytes, collector: tuple[int, Collector]
) -> None:
    port, protocol = collector
    config = quiet_platform_config(*beacon_config(port, "beacon.max_interval=30"))
    platform = await platform_factory(config, fleet_key)
    t0, _ = await asyncio.wait_for(protocol.beacons.get(), 5)
    connection = PlatformConnection(
        config.platform.id, platform.ctx.signaling_url, station_id="op", fleet_key=fleet_key
    )
    await connection.open()
    try:
        # The session bit and the override flip at once; one beacon carries both, at the floor.
        await connection.call("set_manual_override", engaged=True)
        t1, changed = await asyncio.wait_for(protocol.beacons.get(), 5)
        assert changed.status.movrd
        assert changed.status.session
        assert 0.55 <= t1 - t0 < 10
        # A move under the threshold sends nothing; one of 1 m or more does.
        lat, lon = 37.9, 23.6
        platform.bus.publish(topics.POSITION, Position(lat, lon))
        _, located = await asyncio.wait_for(protocol.beacons.get(), 5)
        assert located.position == pytest.approx((lat, lon))
        platform.bus.publish(topics.POSITION, Position(lat + 0.000003, lon))  # ~0.33 m
        with pytest.raises(TimeoutError):
            await asyncio.wait_for(protocol.beacons.get(), 1.5)
        platform.bus.publish(topics.POSITION, Position(lat + 0.00001, lon))  # ~1.1 m
        _, moved = await asyncio.wait_for(protocol.beacons.get(), 5)
        assert moved.position == pytest.approx((lat + 0.00001, lon))
    finally:
        await connection.close()


async def test_no_beacon_when_disabled(
    platform_factory: Factory, fleet_key: bytes, collector: tuple[int, Collector]
) -> None:
    port, protocol = collector
    config = quiet_platform_config(*beacon_config(port), "beacon.enabled=false")
    await platform_factory(config, fleet_key)
    with pytest.raises(TimeoutError):
        await asyncio.wait_for(protocol.beacons.get(), 1.0)


# ------------------------------------------------------------------ station end to end


@pytest.fixture
async def station_with_discovery(fleet_key: bytes) -> AsyncIterator[StationDaemon]:
    port = free_udp_port()
    config = load_config(
        StationConfig,
        None,
        [
            "station.api_port=0",
            f"discovery.port={port}",
            "discovery.bind_host=127.0.0.1",
            "discovery.expiry=1.5",
        ],
    )
    daemon = StationDaemon(config, fleet_key)
    await daemon.start()
    yield daemon
    await daemon.stop()


async def test_station_discovers_connects_by_id_and_forgets_a_silent_platform(
    station_with_discovery: StationDaemon, platform_factory: Factory, fleet_key: bytes
) -> None:
    station = station_with_discovery
    port = station.config.discovery.port
    lost: list[str] = []
    unsubscribe = station.bus.subscribe(topics.PLATFORM_LOST, lambda s: lost.append(s.platform_id))
    config = quiet_platform_config(
        *beacon_config(port, "beacon.max_interval=0.7", "platform.id=rover-7")
    )
    platform = await platform_factory(config, fleet_key)

    async def listed() -> list[dict[str, object]]:
        return await station.ctx.api.call_local("list_platforms")  # type: ignore[no-any-return]

    entries: list[dict[str, object]] = []

    async def poll() -> None:
        while not entries:
            entries.extend(await listed())
            await asyncio.sleep(0.05)

    await asyncio.wait_for(poll(), 5)
    assert entries[0]["id"] == "rover-7"
    assert entries[0]["url"] == platform.ctx.signaling_url

    # Connect by id alone: the URL comes from discovery.
    summary = await station.ctx.api.call_local("connect", platform_id="rover-7")
    assert summary["platform_id"] == "rover-7" or "rover-7" in json.dumps(summary)

    # Forged beacons for the same id are counted and change nothing.
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        forged = codec.encode(sample(platform_id="rover-7", signaling_url="http://evil:1"), None)
        for _ in range(3):
            sock.sendto(forged, ("127.0.0.1", port))
            sock.sendto(b"\x93garbage", ("127.0.0.1", port))
    finally:
        sock.close()
    stats: dict[str, object] = {}

    async def dropped() -> bool:
        stats.update(await station.ctx.api.call_local("discovery_stats"))
        return stats["dropped"]["unsigned"] == 3 and stats["dropped"]["malformed"] == 3  # type: ignore[index]

    for _ in range(100):
        if await dropped():
            break
        await asyncio.sleep(0.05)
    assert stats["dropped"]["unsigned"] == 3  # type: ignore[index]
    assert (await listed())[0]["url"] == platform.ctx.signaling_url

    # The platform goes away: its entry is dropped after the expiry.
    await platform.stop()
    await wait_until(lambda: lost == ["rover-7"], timeout=10)
    assert await listed() == []
    unsubscribe()


async def test_list_command_prints_the_platforms_heard(platform_factory: Factory) -> None:
    port = free_udp_port()
    config = quiet_platform_config(
        *beacon_config(port, "platform.id=rover-9", "beacon.max_interval=0.7"),
        'beacon.destinations=["127.255.255.255"]',  # loopback broadcast: every listener hears
    )
    # The CLI reads the fleet key from the user's state directory (isolated per test).
    key = security.generate_key(security.default_key_path())
    platform = await platform_factory(config, key)
    out = io.StringIO()
    argv = [
        "list",
        "--json",
        "--wait",
        "1.5",
        "--set",
        f"discovery.port={port}",
    ]

    def run() -> int:
        with contextlib.redirect_stdout(out):
            return cli.main(argv)

    code = await asyncio.to_thread(run)
    assert code == 0, out.getvalue()
    [entry] = json.loads(out.getvalue())
    assert entry["id"] == "rover-9"
    assert entry["url"] == platform.ctx.signaling_url


async def test_sim_platform_beacon_carries_battery_controller_gps_and_position(
    platform_factory: Factory, fleet_key: bytes, collector: tuple[int, Collector]
) -> None:
    """The status word and position come from the drivers: controller, battery, GPS fix."""
    port, protocol = collector
    config = quiet_platform_config(
        *beacon_config(port, "beacon.max_interval=0.7"),
        "sim.enabled=true",
        "motor.enabled=true",
        "gps.enabled=true",
    )
    await platform_factory(config, fleet_key)

    async def complete() -> Beacon:
        while True:
            _, beacon = await protocol.beacons.get()
            status = beacon.status
            if status.controller and status.gps_fix and beacon.position is not None:
                if status.battery is not Battery.UNKNOWN:
                    return beacon

    beacon = await asyncio.wait_for(complete(), 20)
    assert beacon.status.battery is Battery.MEDIUM  # the simulated 24.6 V pack under load
    assert beacon.position == pytest.approx((config.sim.latitude, config.sim.longitude), abs=1e-4)
    assert not beacon.status.fault


@settings(max_examples=200, deadline=None)
@given(
    st.sampled_from(["truncate", "extend", "flip"]),
    st.integers(0, 99),
    st.integers(1, 255),
    st.binary(min_size=1, max_size=8),
)
def test_a_changed_signed_beacon_is_refused_and_counted(
    how: str, position: int, flip: int, extra: bytes
) -> None:
    good = codec.encode(sample(), KEY)
    if how == "truncate":
        bad = good[: position % len(good)]
    elif how == "extend":
        bad = good + extra
    else:
        changed = bytearray(good)
        changed[position % len(good)] ^= flip
        bad = bytes(changed)
    with pytest.raises(BeaconError):
        codec.decode(bad, KEY)
    directory = PlatformDirectory(KEY, 4.0)
    directory.receive(bad, "127.0.0.1")
    stats = directory.stats()
    assert stats["received"] == 1
    assert stats["accepted"] == 0
    assert sum(stats["dropped"].values()) == 1
