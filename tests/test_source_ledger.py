"""One account per source address for every byte the robot sends on its behalf
(brasidas.admission.SourceLedger): MAVLink answers to a stranger, the video a MAVLink request
starts, recording downloads. Each path is checked against what actually went on the wire, so
a path that bypassed the account would show bytes the account never saw."""

from __future__ import annotations

import asyncio
import hashlib
import socket
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from conftest import wait_until
from mavlink_gcs import Gcs, sim_rover_config
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas.admission import STRANGER_WINDOW_S, SourceLedger
from platformd.app import PlatformDaemon
from platformd.mavlink.vehicle import CameraInfo, MavlinkVehicle, StartVideo
from platformd.recording_download import CHUNK
from platformd.session_table import Session

Factory = Callable[..., Awaitable[PlatformDaemon]]
STRANGER = "127.0.0.3"
KEY = hashlib.sha256(b"fleet passphrase").digest()


def test_a_stranger_is_paid_only_with_what_it_sent_whatever_the_path() -> None:
    ledger = SourceLedger()
    ledger.received("192.0.2.7", 100, 0.0)
    assert ledger.stranger_send("192.0.2.7", 60, 1.0)
    assert not ledger.stranger_send("192.0.2.7", 60, 2.0)  # 40 left: all or nothing
    assert ledger.stranger_send("192.0.2.7", 40, 2.0, "rtp")  # any path spends the same credit
    assert ledger.sent_to("192.0.2.7") == {"mavlink": 60, "rtp": 40, "download": 0}
    assert ledger.counters["stranger_bytes_held"] == 60
    # A new window: unspent credit goes with the old one, silence earns nothing.
    ledger.received("192.0.2.7", 50, 3.0)
    assert not ledger.stranger_send("192.0.2.7", 10, 3.0 + STRANGER_WINDOW_S)
    # Another address's credit is its own.
    assert not ledger.stranger_send("192.0.2.8", 1, 4.0)
    # A stream: only for a trusted source; one that is no longer trusted stops when its
    # credit does not cover what was sent (counted all the same).
    assert not ledger.admits_stream("192.0.2.7", False)
    assert ledger.admits_stream("192.0.2.9", True)
    assert ledger.stream_sent("192.0.2.9", 10**6, True, 5.0)
    assert not ledger.stream_sent("192.0.2.9", 10**6, False, 6.0)
    assert ledger.sent_to("192.0.2.9")["rtp"] == 2 * 10**6
    assert ledger.counters["streams_refused"] == 1
    assert ledger.counters["streams_stopped"] == 1


def test_the_table_of_sources_is_bounded() -> None:
    ledger = SourceLedger(max_sources=8)
    for n in range(100):  # a flood of made-up source addresses
        ledger.received(f"10.0.{n}.1", 1000, 0.0)
    assert len(ledger.accounts) == 8
    assert ledger.counters["sources_forgotten"] == 92
    # The forgotten ones lost their credit (never gained any).
    assert not ledger.stranger_send("10.0.0.1", 1, 0.0)


def test_each_source_gets_its_part_of_the_download_rate() -> None:
    """Sixteen parallel downloads from one host do not crowd out another host's one: over
    the same time each host gets half, and both together never more than the rate."""
    rate = 1024 * 1024
    ledger = SourceLedger(download_rate=rate)
    due = {("A", n): 0.0 for n in range(16)} | {("B", 0): 0.0}
    sent = {"A": 0, "B": 0}
    now = 0.0
    while now < 10.0:  # each download sends its next chunk when its slot comes
        (host, n), now = min(due.items(), key=lambda item: item[1])
        delay = ledger.reserve_download(host, CHUNK, now)
        due[(host, n)] = now + delay + 1e-6
        if now + delay <= 10.0:
            sent[host] += CHUNK
    assert sent["A"] + sent["B"] <= rate * 10 + 17 * CHUNK  # give or take what was in flight
    assert sent["B"] >= 0.45 * rate * 10
    assert sent["A"] >= 0.45 * rate * 10
    assert ledger.sent_to("B")["download"] >= sent["B"]


def test_one_source_mixing_mavlink_video_and_downloads_stays_within_one_budget() -> None:
    """A stranger's MAVLink answers, its video request and downloads charged to the same
    address: the vehicle's answers are exactly what the account saw, the video is refused by
    the account, and the answers never exceed the bytes the source sent."""
    ledger = SourceLedger(download_rate=64 * 1024)
    vehicle = MavlinkVehicle(
        1, key=KEY, camera=CameraInfo(640, 480, 30.0, 1500, 5600), ledger=ledger
    )
    vehicle.state.params = [(f"P{i}", float(i), mavlink.MAV_PARAM_TYPE_REAL32) for i in range(60)]
    source = ("192.0.2.7", 14550)
    mav = mavlink.MAVLink(None, 249, 190)
    asks = [
        mavlink.MAVLink_param_request_list_message(1, 1),
        mavlink.MAVLink_command_long_message(
            1, 100, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, 269, 0, 0, 0, 0, 0, 0
        ),
        mavlink.MAVLink_mission_request_list_message(1, 1, 0),
    ]
    received = wire = 0
    now = next_chunk = 0.0
    for step in range(200):
        frame = bytes(asks[step % 3].pack(mav))
        received += len(frame)
        requests = vehicle.feed(frame, source, now)
        assert not [r for r in requests if isinstance(r, StartVideo)]
        vehicle.tick(now)
        wire += sum(len(data) for data, peer in vehicle.take() if peer[0] == source[0])
        if now >= next_chunk:  # a download sends its next chunk once the last one's slot came
            next_chunk = now + ledger.reserve_download(source[0], CHUNK, now)
        now += 0.1
    sent = ledger.sent_to(source[0])
    assert sent["mavlink"] == wire  # nothing reached the wire past the account
    assert 0 < wire <= received
    assert sent["rtp"] == 0
    assert ledger.counters["streams_refused"] == 200 // 3 + 1
    # Downloads (a session's) at the address's share: the whole rate here, no more.
    assert sent["download"] <= 64 * 1024 * now + CHUNK
    assert sent["mavlink"] + sent["rtp"] + sent["download"] <= received + 64 * 1024 * now + CHUNK


class _Counter(asyncio.DatagramProtocol):
    def __init__(self) -> None:
        self.bytes = 0

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.bytes += len(data)


@pytest.fixture
async def gcs() -> AsyncIterator[Gcs]:
    station = await Gcs.open()
    yield station
    station.close()


async def _stranger_gcs() -> Gcs:
    loop = asyncio.get_running_loop()
    _, stranger = await loop.create_datagram_endpoint(
        lambda: Gcs(254, 190), local_addr=(STRANGER, 0)
    )
    return stranger


def _free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


async def test_every_path_is_charged_to_its_source_on_a_running_platform(
    platform_factory: Factory, tmp_path: Path, gcs: Gcs
) -> None:
    """A running platform: a configured ground station's video is charged to its address as
    the NavCam sends it; a stranger at another address that also holds a session mixes
    MAVLink requests and a download, and its account is exactly what it got on the wire,
    within what it sent plus its download share."""
    recordings = tmp_path / "recordings"
    recordings.mkdir()
    (recordings / "2020-01-01T00-00-00Z.mcap").write_bytes(b"\0" * (640 * 1024))
    video_port = _free_udp_port()
    rate_kib = 256
    daemon = await platform_factory(
        sim_rover_config(
            tmp_path,
            gcs.port,
            "navcam.enabled=true",
            f"navcam.port={video_port}",
            "recorder.enabled=true",
            f"recorder.dir={recordings}",
            f"recorder.download_kib_s={rate_kib}",
        ),
        None,
    )
    ledger = daemon.ctx.egress
    loop = asyncio.get_running_loop()
    video, counter = await loop.create_datagram_endpoint(
        _Counter, local_addr=("127.0.0.1", video_port)
    )
    stranger = await _stranger_gcs()
    try:
        await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 100)
        ack = await gcs.command(
            mavlink.MAV_CMD_REQUEST_MESSAGE,
            mavlink.MAVLINK_MSG_ID_VIDEO_STREAM_INFORMATION,
            component=100,
        )
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED
        await wait_until(lambda: counter.bytes > 20_000, 30)
        seen = counter.bytes
        # The configured station's video, charged to its address as it goes.
        await wait_until(lambda: ledger.sent_to("127.0.0.1")["rtp"] >= seen, 10)

        # The stranger at 127.0.0.3: a session of its own there (as a station's would be),
        # MAVLink requests and a download at once.
        token = "t" * 32
        now = time.monotonic()
        daemon.ctx.sessions.open(Session(token, "st-3", STRANGER, None, now, now))
        assert daemon.ctx.mavlink_port
        stranger.vehicle = ("127.0.0.1", daemon.ctx.mavlink_port)
        url = f"{daemon.ctx.signaling_url}/recordings/2020-01-01T00-00-00Z.mcap"
        started = loop.time()

        async def download() -> int:
            connector = aiohttp.TCPConnector(local_addr=(STRANGER, 0))
            async with aiohttp.ClientSession(connector=connector) as http:
                async with http.get(url, headers={"X-Brasidas-Session": token}) as response:
                    assert response.status == 200
                    return len(await response.read())

        fetching = asyncio.create_task(download())
        asks: list[Any] = [
            mavlink.MAVLink_param_request_list_message(1, 1),
            mavlink.MAVLink_command_long_message(
                1, 100, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, 269, 0, 0, 0, 0, 0, 0
            ),
        ]
        for n in range(40):
            stranger.send(asks[n % 2])
            await asyncio.sleep(0.02)
        body = await asyncio.wait_for(fetching, 30)
        elapsed = loop.time() - started
        sent = sum(len(frame) for frame in stranger.frames)
        # What reached the stranger on the wire is what its account saw, path by path.
        await wait_until(lambda: ledger.sent_to(STRANGER)["mavlink"] == stranger.bytes_received)
        account = ledger.sent_to(STRANGER)
        assert account["download"] == body == 640 * 1024
        assert account["rtp"] == 0  # its video requests were refused by the account
        assert 0 < stranger.bytes_received <= sent
        assert sum(account.values()) <= sent + rate_kib * 1024 * elapsed + CHUNK
        counters = daemon.ctx.telemetry.counters["mavlink"]()
        assert counters["streams_refused"] >= 1
        assert counters["video_refused"] >= 1
    finally:
        stranger.close()
        video.close()
