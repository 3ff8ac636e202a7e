"""A takeover is told at once (issue 13, item 3): two station daemons on one platform, over
real sockets. The previous holder hears ``movrd --force`` from the telemetry the platform
pushes the moment control changes hands (confirmed by a heartbeat), not at its next heartbeat:
here heartbeats are 30 s apart and periodic telemetry 5 s apart."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable

from conftest import quiet_platform_config, running_station, wait_until

from brasidas import topics
from brasidas.messages import StationNotification
from platformd.app import PlatformDaemon
from stationd.telemetry import CONTROL_TAKEN

Factory = Callable[..., Awaitable[PlatformDaemon]]
SLOW_LINK = ("telemetry.rate_hz=0.2", "telemetry.silence_s=60")
"""A station asking for a snapshot every 5 s, and not alarmed by that."""


async def test_the_previous_holder_is_told_of_a_forced_takeover_at_once(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(
        quiet_platform_config("signaling.heartbeat_interval=30", "signaling.session_timeout=120"),
        fleet_key,
    )
    platform_id, url = daemon.config.platform.id, daemon.ctx.signaling_url
    async with (
        running_station(fleet_key, "station.id=alpha", *SLOW_LINK) as alpha,
        running_station(fleet_key, "station.id=bravo", *SLOW_LINK) as bravo,
    ):
        notes: list[tuple[float, StationNotification]] = []
        alpha.bus.subscribe(
            topics.STATION_NOTIFICATIONS, lambda note: notes.append((time.monotonic(), note))
        )
        for station in (alpha, bravo):
            await station.ctx.api.call_local("connect", platform_id=platform_id, url=url)
        # alpha drives; both get their first snapshot (then the next is 5 s away).
        answer = await alpha.ctx.api.call_local("movrd", platform_id=platform_id, engaged=True)
        assert answer["accepted"], answer
        links = [station.ctx.connections[platform_id] for station in (alpha, bravo)]
        for station in (alpha, bravo):
            while not (await station.ctx.api.call_local("get_telemetry", platform_id=platform_id))[
                "link"
            ]["received"]:
                await asyncio.sleep(0.02)
        assert links[0].control
        assert not links[1].control
        # bravo takes control with --force.
        forced = time.monotonic()
        answer = await bravo.ctx.api.call_local(
            "movrd", platform_id=platform_id, engaged=True, force=True
        )
        assert answer["accepted"], answer
        await wait_until(lambda: _taken(notes), timeout=2.5)
        at, note = next((at, n) for at, n in notes if n.code == CONTROL_TAKEN)
        assert note.message == f"control of {platform_id} taken by station bravo"
        assert at - forced < 2.5  # long before alpha's next heartbeat (30 s) or snapshot (5 s)
        assert not links[0].control
        assert links[0].controller == "bravo"
        assert not links[0].manual_override  # its stream of $PVEL stops
        assert daemon.ctx.authority.station_id == "bravo"
        assert links[1].control


def _taken(notes: list[tuple[float, StationNotification]]) -> bool:
    return any(note.code == CONTROL_TAKEN and note.active for _, note in notes)
