"""The NavCam at 5 fps (every patrol, every moment the override is off) across hosts through
the link emulator: a packet lost on the link is asked for again until it arrives, within the
frame's budget, though the next packet (the next frame's) is 200 ms away."""

from __future__ import annotations

import time
from collections.abc import AsyncIterator, Iterator
from pathlib import Path
from typing import Any

import pytest
from netns import Daemon, Fleet, network_fixture, requires_netns, wait_for

from brasidas.netem.core import Profile
from brasidas.netem.netns import TestNetwork

pytestmark = requires_netns
network = network_fixture("vi5")

ROVER = "rover-5"
FPS = 5


@pytest.fixture(scope="module")
def fleet(network: TestNetwork, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fleet]:
    fleet = Fleet(network, Path(tmp_path_factory.mktemp("video5")))
    station_host = network.add_host("st")
    rover_host = network.add_host("rover", impaired=True)
    fleet.platform(
        rover_host,
        ROVER,
        "gps.enabled=false",
        "imu.enabled=false",
        "audio.enabled=false",
        "recorder.enabled=false",
        f"navcam.idle_framerate={FPS}",  # no override engaged: the idle rate is what is sent
        "navcam.sim_pattern=smpte",
        "navcam.sim_motion=4",
    )
    fleet.station(station_host, "station-1")
    yield fleet
    fleet.stop()


def _station(fleet: Fleet) -> Daemon:
    return next(d for d in fleet.daemons if d.name == "station-1")


async def _receiver(fleet: Fleet) -> dict[str, Any]:
    receivers = await fleet.api(_station(fleet), "receivers")
    return next(r for r in receivers if r["platform_id"] == ROVER and r["stream"] == "navcam")


@pytest.fixture
async def watching(fleet: Fleet) -> AsyncIterator[Fleet]:
    """The station receiving the rover's 5 fps NavCam over a link losing 10 % each way."""
    station = _station(fleet)
    await fleet.wait_listening(station, "127.0.0.1", 8780)
    await fleet.connect(station, ROVER)
    lossy = Profile(loss=0.10, delay=0.01)
    fleet.net.impair("rover", down=lossy, up=lossy)
    answer = await fleet.api(station, "receive", platform_id=ROVER, stream="navcam")
    assert answer["state"] == "playing", answer
    yield fleet
    fleet.net.impair("rover", down=Profile(), up=Profile())
    await fleet.api(station, "stop_receive", platform_id=ROVER, stream="navcam")


async def test_a_packet_lost_at_5_fps_is_rebuilt_before_its_frame_is_given_up(
    watching: Fleet,
) -> None:
    fleet = watching

    async def started() -> bool:
        return (await _receiver(fleet))["frames"] >= 5

    await wait_for(started, timeout=30, step=0.5)
    before = await _receiver(fleet)
    since = time.monotonic()

    async def enough() -> bool:
        return (await _receiver(fleet))["frames"] >= before["frames"] + 60

    await wait_for(enough, timeout=40, step=0.5)
    rx = await _receiver(fleet)
    seconds = time.monotonic() - since
    lost_on_link = rx["rtp_lost"] - before["rtp_lost"]
    given_up = rx["repair"]["lost"] - before["repair"]["lost"]
    # Packets went missing on the link (a tenth of ~30 a second) ...
    assert lost_on_link >= 10, rx
    # ... and each was asked for again until it came, within the 200 ms a frame may wait.
    # With the jitter buffer's own retry timer (never shorter than the packet spacing:
    # 190 ms at 5 fps) each packet had one try, and a fifth of those failed (10 % lost each
    # way): a frame given up on, then frozen to a keyframe.
    assert given_up <= max(1, lost_on_link // 50), (given_up, lost_on_link, rx)
    shown = (rx["frames"] - before["frames"]) / (FPS * seconds)
    assert shown >= 0.9, (shown, rx)
