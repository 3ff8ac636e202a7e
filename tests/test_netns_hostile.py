"""A hostile mesh (issue 19): what an attacker on the same network, and an observer station,
cannot do to the station holding control. Hosts are network namespaces on a bridge
(tests/hostile.py): the platform (``--sim``, its NavCam a test pattern), the holder behind a
link emulator, an observer, and an attacker without the fleet key."""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Callable

import pytest
from hostile import (
    PLATFORM,
    VELOCITY_PORT,
    HostileRig,
    count_for,
    datagram_counter,
    hostile_rig_fixture,
)
from netns import RpcFailed, network_fixture, requires_netns, wait_for

from brasidas.netem.netns import TestNetwork
from brasidas.netem.relay import UP, Datagram

pytestmark = requires_netns
network = network_fixture("hst")
rig = hostile_rig_fixture("hst")

HOLD_AFTER = 1.5  # failsafe.hold_after's default
CUT = 3.0


@pytest.fixture
async def connected(rig: HostileRig) -> AsyncIterator[HostileRig]:
    """Both stations connected over a clean link; the override released afterwards."""
    relay = rig.net.hosts["holder"].relay
    assert relay is not None
    relay.clear()
    await rig.connect_all()
    yield rig
    relay.clear()
    await rig.release()


async def test_a_replay_during_a_cut_never_holds_off_the_failsafe(connected: HostileRig) -> None:
    """Item 1: while the holder's link is cut, the attacker replays the holder's captured
    ``$PVEL`` from the holder's own address. The ladder holds at ``hold_after`` all the same,
    and when the link returns the station's stream (still 0.5 forward) moves nothing."""
    rig = connected
    holder = rig.net.hosts["holder"]
    relay = holder.relay
    assert relay is not None
    await rig.engage()

    async def keep_driving() -> None:
        while True:
            with contextlib.suppress(RpcFailed):
                await rig.api(
                    rig.holder, "teleop_set", platform_id=PLATFORM, linear=0.5, angular=0.0
                )
            await asyncio.sleep(0.1)

    async def motors_desired() -> list[int]:
        return list((await rig.section(rig.observer, "motor")).get("desired") or [])

    async def moving() -> bool:
        return any(level != 0 for level in await motors_desired())

    steps: list[tuple[float, str]] = []
    desired_after: list[list[int]] = []
    async with asyncio.TaskGroup() as group:
        driver = group.create_task(keep_driving(), name="drive")
        await wait_for(moving, 20, step=0.1)

        def holder_velocity() -> list[Datagram]:
            return [
                d
                for _, d in rig.capture.select(UP, "udp", VELOCITY_PORT)
                if d.destination[0] == rig.platform_address
            ]

        await wait_for(lambda: len(holder_velocity()) >= 20, 10)
        captured = holder_velocity()[-40:]
        link_before = await rig.section(rig.observer, "velocity_link")
        sent_before = rig.attacker.sent
        relay.cut()
        cut_at = time.monotonic()

        async def replay() -> None:
            for d in itertools.cycle(captured):
                rig.attacker.send_as(d.source, d.destination, d.payload)
                await asyncio.sleep(0.05)

        replayer = group.create_task(replay(), name="replay")
        # The observer watches the ladder through its own telemetry while the holder is cut.
        while time.monotonic() - cut_at < CUT:
            step = (await rig.section(rig.observer, "failsafe")).get("step")
            if step is not None:
                steps.append((time.monotonic() - cut_at, str(step)))
            await asyncio.sleep(0.1)
        relay.restore()
        replayer.cancel()
        replayed = rig.attacker.sent - sent_before
        link_during = await rig.section(rig.observer, "velocity_link")
        # The link is back and the station streams 0.5 forward again: nothing moves.
        restored_at = time.monotonic()
        while time.monotonic() - restored_at < 2.0:
            desired_after.append(await motors_desired())
            await asyncio.sleep(0.1)
        driver.cancel()
    hold = next((at for at, step in steps if step == "hold"), None)
    dropped = {
        reason: link_during["dropped"].get(reason, 0) - count
        for reason, count in link_before["dropped"].items()
        if link_during["dropped"].get(reason, 0) != count
    }
    print(
        f"\nreplayed {replayed} $PVEL from {holder.address} during a {CUT} s cut: "
        f"failsafe steps seen {sorted({s for _, s in steps})}, hold seen at "
        f"{'never' if hold is None else f'{hold:.2f} s'} (hold_after {HOLD_AFTER} s); "
        f"motors after restore {desired_after[-1] if desired_after else None}; "
        f"counted as dropped during the cut: {dropped}"
    )
    assert hold is not None, steps
    assert hold < CUT
    # Every replayed packet was dropped and counted, by its reason (telemetry lags by at most
    # velocity.stats_interval, 1 s: most of them at least).
    assert sum(dropped.get(r, 0) for r in ("out_of_order", "stale", "held")) >= replayed // 2
    assert all(level == 0 for levels in desired_after for level in levels), desired_after


@pytest.fixture
async def holder_video(connected: HostileRig) -> AsyncIterator[Callable[[], int]]:
    """The holder receives the NavCam on a socket of its host; the drain of that socket.
    Every station's NavCam copy is stopped afterwards."""
    rig = connected
    sock, drain = datagram_counter(rig.net.hosts["holder"])
    port = sock.getsockname()[1]
    try:
        await rig.api(rig.holder, "stream_start", platform_id=PLATFORM, stream="navcam", port=port)
        await wait_for(lambda: drain() > 0, 20, step=0.1)
        yield drain
    finally:
        for station in (rig.observer, rig.holder):
            with contextlib.suppress(RpcFailed):
                await rig.api(station, "stream_stop", platform_id=PLATFORM, stream="navcam")
        sock.close()


async def test_an_observer_cannot_resume_a_stream_the_holder_paused(
    connected: HostileRig, holder_video: Callable[[], int]
) -> None:
    """Item 4: pausing and resuming the holder's streams is control; an observer's start (the
    method, or system command 10.1) adds its own copy, paused with the rest."""
    rig = connected
    drain = holder_video
    paused = await rig.api(rig.holder, "stream_pause", platform_id=PLATFORM, stream="navcam")
    assert paused["state"] == "paused"
    await count_for(drain, 0.5)  # what was on its way
    assert await count_for(drain, 1.0) == 0
    started = await rig.api(rig.observer, "stream_start", platform_id=PLATFORM, stream="navcam")
    command = await rig.api(rig.observer, "command", platform_id=PLATFORM, group=10, command=1)
    during = await count_for(drain, 3.0)
    print(
        f"\nobserver's start on the paused NavCam: {started['state']}, 10.1 {command}; "
        f"holder received {during} datagrams in 3 s"
    )
    assert during == 0
    assert started["state"] == "paused"
    # The holder resumes: control works.
    await rig.api(rig.holder, "stream_start", platform_id=PLATFORM, stream="navcam")
    assert await count_for(drain, 2.0) > 0


@pytest.mark.parametrize("target", ["multicast", "holder", "third"])
async def test_an_observer_cannot_point_a_stream_at_others(
    connected: HostileRig, holder_video: Callable[[], int], target: str
) -> None:
    """Item 5: a station's stream goes to its own address (or loopback, or what config names):
    a multicast group the platform has no route to (which would fail the sink every station's
    copy shares), another station (doubling its traffic) and a third address (an amplifier) are
    refused, by the method and by system command 10.1; the holder's video goes on."""
    rig = connected
    drain = holder_video
    host = {
        "multicast": "224.0.0.1",
        "holder": rig.net.hosts["holder"].address,
        "third": "198.18.0.4",
    }[target]
    before = await count_for(drain, 1.0)
    with pytest.raises(RpcFailed) as refused:
        await rig.api(
            rig.observer,
            "stream_start",
            platform_id=PLATFORM,
            stream="navcam",
            host=host,
            port=9,
        )
    command = await rig.api(
        rig.observer, "command", platform_id=PLATFORM, group=10, command=1, payload=f"host={host}"
    )
    after = await count_for(drain, 2.0)
    print(
        f"\nobserver's NavCam to {host}: {refused.value.error.get('message')}; "
        f"10.1: {command}; holder received {before}/s before, {after / 2:.0f}/s after"
    )
    assert after > 0  # the shared sink never failed
    assert "caller's own address" in str(refused.value.error.get("message"))
    assert command["accepted"] is False
    assert "caller's own address" in command["reason"]


SINK_PROBE = """
import asyncio, socket, sys
from brasidas.media.video import VideoOut, VideoSettings

async def main(address: str) -> None:
    receiver = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    receiver.bind((address, 0))
    receiver.settimeout(0.2)
    port = receiver.getsockname()[1]
    settings = VideoSettings(host=address, port=port, width=160, height=120, framerate=10,
                             camera_framerate=10, test_source=True)
    stream = VideoOut("navcam", settings)
    await stream.start()
    # Another session's copy to a multicast group this host has no route to, added live.
    stream.set_destinations([(address, port), ("224.0.0.1", port)])
    received = 0
    loop = asyncio.get_running_loop()
    deadline = loop.time() + 3
    while loop.time() < deadline:
        try:
            await asyncio.to_thread(receiver.recv, 65536)
            received += 1
        except TimeoutError:
            pass
    print(stream.state.value, received, stream.reason, flush=True)
    await stream.stop()

asyncio.run(main(sys.argv[1]))
"""


async def test_a_destination_without_a_route_never_fails_the_shared_sink(
    network: TestNetwork,
) -> None:
    """Item 5: a copy to a multicast group the host has no route for (one that config allowed,
    or whose route went away) fails its own packets only: the sink every station's copy shares
    keeps sending to the others."""
    host = network.add_host("sink")
    process = host.spawn(
        [sys.executable, "-c", SINK_PROBE, host.address],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
    )
    out, err = await asyncio.to_thread(process.communicate, timeout=120)
    state, received, *reason = out.decode().split(maxsplit=2) or ["", "0"]
    print(
        f"\nNavCam with a copy to 224.0.0.1 (no route): {state}, {received} datagrams to the other copy in 3 s {reason}"
    )
    assert state == "playing", err.decode()[-2000:]
    assert int(received) > 0
