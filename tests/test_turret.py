"""The turret payload (issue 13): its line protocol against the simulated microcontroller on a
real pty, and engagement only under manual override (R-0.5) on a --sim platform."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
import serial_asyncio
from conftest import free_tcp_port, quiet_platform_config, wait_until

from brasidas.codecs import turret
from brasidas.codecs.turret import Drop, Line, LineDecoder
from platformd.app import PlatformDaemon
from platformd.failsafe import FailsafeLadder
from platformd.payloads.turret import FIRE, TurretDriver, TurretError
from platformd.sim.turret import TurretDevice, TurretSimulator
from stationd.client import PlatformConnection

Factory = Callable[..., Awaitable[PlatformDaemon]]


def test_lines_round_trip_and_bad_checksums_are_dropped_and_counted() -> None:
    decoder = LineDecoder()
    good = turret.command(7, "AIM", 12.5, -3.0)
    assert good == b"$C,7,AIM,12.5,-3.0*" + good[-3:]
    bad = good[:-3] + (b"00" if good[-3:-1] != b"00" else b"11") + b"\n"
    assert decoder.feed(good + bad + b"noise\n") == [
        Line("C", ("7", "AIM", "12.5", "-3.0")),
        Drop.BAD_CHECKSUM,
        Drop.MALFORMED,
    ]
    assert decoder.dropped[Drop.BAD_CHECKSUM] == 1
    device = TurretDevice()
    assert device.feed(bad, now=0.0) == b""
    assert device.log == []  # never acted on


@pytest.fixture
async def line() -> AsyncIterator[tuple[TurretSimulator, TurretDriver]]:
    simulator = TurretSimulator(TurretDevice(watchdog_s=0.3))
    simulator.start()
    loop = asyncio.get_running_loop()
    transport, driver = await serial_asyncio.create_serial_connection(
        loop, lambda: TurretDriver(ack_timeout=0.1), simulator.path, baudrate=115200
    )
    try:
        yield simulator, driver
    finally:
        transport.close()
        simulator.close()


class _AckingTransport(asyncio.WriteTransport):
    """A line whose microcontroller acknowledges each command in the very loop turn that
    the driver's task is cancelled: the race ``asyncio.wait_for`` (3.11) loses."""

    def __init__(self, driver: TurretDriver, task: Callable[[], asyncio.Task[Any]]) -> None:
        super().__init__()
        self.driver, self.task = driver, task

    def write(self, data: Any) -> None:
        seq = int(bytes(data).split(b",")[1])

        def ack_and_cancel() -> None:
            self.driver.data_received(turret.encode("A", seq, "OK", 0.0, 0.0, 0))
            self.task().cancel()

        asyncio.get_running_loop().call_soon(ack_and_cancel)


async def test_a_cancellation_that_comes_with_the_acknowledgement_stops_the_driver() -> None:
    """The payload actor must stop when cancelled, even when the microcontroller's answer
    arrives in the same loop turn (wait_for returned the answer and swallowed the
    cancellation: the actor pinged on past the daemon's stop, seen as a leaked task)."""
    driver = TurretDriver(ack_timeout=1.0)
    sending: asyncio.Task[Any] | None = None

    def current() -> asyncio.Task[Any]:
        assert sending is not None
        return sending

    driver.connection_made(_AckingTransport(driver, current))
    sending = asyncio.get_running_loop().create_task(driver.send("PING"))
    with pytest.raises(asyncio.CancelledError):
        await sending


async def test_lost_and_corrupted_acknowledgements_are_resent_and_acted_on_once(
    line: tuple[TurretSimulator, TurretDriver],
) -> None:
    simulator, driver = line
    simulator.device.ignore_next = 1  # the command is lost on the way
    await driver.send("AIM", 10.0, 5.0)
    simulator.corrupt_next = 1  # the acknowledgement arrives with a bad checksum
    await driver.send("FIRE")
    assert simulator.device.log == ["AIM,10.0,5.0", "FIRE"]  # each acted on once
    assert driver.counters["resent"] == 2
    assert driver.decoder.dropped[Drop.BAD_CHECKSUM] == 1
    assert driver.state == (10.0, 5.0, True)
    with pytest.raises(TurretError, match="out of range"):
        await driver.send("AIM", 500.0, 0.0)
    simulator.device.ignore_next = 5
    with pytest.raises(TurretError, match="no acknowledgement after 3 tries"):
        await driver.send("SAFE")


async def test_the_microcontroller_watchdog_releases_the_trigger_when_the_driver_is_silent(
    line: tuple[TurretSimulator, TurretDriver],
) -> None:
    simulator, driver = line
    await driver.send("FIRE")
    assert simulator.device.trigger
    # The driver goes silent (no pings): the microcontroller lets go by itself, and says so.
    await wait_until(lambda: driver.counters["watchdog"] == 1)
    assert simulator.device.trigger is False
    assert simulator.device.log[-1] == "WATCHDOG"


async def station(daemon: PlatformDaemon, key: bytes, name: str) -> PlatformConnection:
    conn = PlatformConnection(
        daemon.config.platform.id, daemon.ctx.signaling_url, station_id=name, fleet_key=key
    )
    await conn.open()
    return conn


async def command(conn: PlatformConnection, code: int, payload: str = "") -> dict[str, Any]:
    answer: dict[str, Any] = await conn.call(
        "issue_system_command", group=100, command=code, payload=payload
    )
    return answer


async def test_engagement_only_from_the_override_holder_under_override(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(
        quiet_platform_config(
            "sim.enabled=true",
            'payload.enabled=["turret"]',
            "failsafe.hold_after=50",
            "signaling.session_timeout=60",  # above hold_after (the config refuses less)
            "failsafe.release_after=100",
        ),
        fleet_key,
    )
    simulator = daemon.ctx.sim.turret
    assert simulator is not None
    device = simulator.device
    a = await station(daemon, fleet_key, "alpha")
    b = await station(daemon, fleet_key, "bravo")
    try:
        assert a.capabilities["payload_groups"] == [100]
        fire = next(c for c in a.capabilities["payload_commands"] if c["name"] == "fire")
        assert fire == {"code": "100.1", "name": "fire", "format": "", "engagement": True}
        await wait_until(lambda: daemon.ctx.commands.owner(FIRE) == "turret")

        # Autonomous Mode: aiming is allowed to the controller, the trigger is not.
        assert (await command(a, 0, "az=20,el=5"))["accepted"]
        refused = await command(a, 1)
        assert not refused["accepted"]
        assert refused["reason"] == (
            "turret fire (100.1) refused: engagement only under manual override (Autonomous Mode)"
        )
        # Under alpha's override: bravo (an observer) can neither aim nor fire.
        assert (await a.call("set_manual_override", engaged=True)) is True
        for code in (0, 1):
            answer = await command(b, code, "az=1,el=1")
            assert "control held by station alpha" in answer["reason"]
        accepted = await command(a, 1)
        assert accepted["accepted"]
        assert accepted["result"]["trigger"] is True
        assert device.trigger
        # Releasing the override makes the turret safe at once.
        assert (await a.call("set_manual_override", engaged=False)) is True
        await wait_until(lambda: not device.trigger)
        # A failsafe step: safe at once, and the trigger refused until the operator re-engages.
        assert (await a.call("set_manual_override", engaged=True)) is True
        assert (await command(a, 1))["accepted"]
        ladder = FailsafeLadder(daemon.ctx)
        ladder.tick(daemon.ctx.sessions.sessions[a.session_id].last_seen + 60)
        await wait_until(lambda: not device.trigger)
        refused = await command(a, 1)
        assert "failsafe hold" in refused["reason"]
        assert daemon.ctx.authority.counters["engagement_refused"] == 2
        report = (await a.call("get_telemetry_report"))["turret"]
        assert report["connected"]
        assert report["trigger"] is False
        assert report["counters"]["safe"] >= 2
        assert report["azimuth"] == 20.0
        # The microcontroller never saw a refused command: two FIREs, both accepted ones.
        assert [entry for entry in device.log if entry == "FIRE"] == ["FIRE", "FIRE"]
        assert device.log[0] == "AIM,20.0,5.0"
    finally:
        await a.close()
        await b.close()


async def test_the_turret_registers_the_thermal_camera_as_its_stream(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    camera = f"rtsp://127.0.0.1:{free_tcp_port()}/thermal"  # offline: the stream fails, listed
    turret_with_camera = await platform_factory(
        quiet_platform_config(
            "sim.enabled=true",
            'payload.enabled=["turret"]',
            "payload_camera.enabled=true",
            f"payload_camera.url={camera}",
        ),
        fleet_key,
    )
    camera_only = await platform_factory(
        quiet_platform_config(
            "platform.id=camera-only",
            "payload_camera.enabled=true",
            f"payload_camera.url={camera}",
        ),
        fleet_key,
    )
    turret_only = await platform_factory(
        quiet_platform_config(
            "platform.id=turret-only", "sim.enabled=true", 'payload.enabled=["turret"]'
        ),
        fleet_key,
    )
    a = await station(turret_with_camera, fleet_key, "alpha")
    b = await station(camera_only, fleet_key, "alpha")
    c = await station(turret_only, fleet_key, "alpha")
    try:
        turret_entry = {"name": "turret", "groups": [100], "streams": ["payload_camera"]}
        assert a.capabilities["payloads"] == [turret_entry]
        assert "payload_camera" in [s["name"] for s in a.capabilities["streams"]]
        # A platform without the payload lists none, its camera staying a plain stream;
        # one whose turret has no camera lists the turret without a stream.
        assert b.capabilities["payloads"] == []
        assert b.capabilities["payload_groups"] == []
        assert "payload_camera" in [s["name"] for s in b.capabilities["streams"]]
        assert c.capabilities["payloads"] == [{**turret_entry, "streams": []}]
        # Telemetry: the turret's section carries its stream's state, live.
        report = await a.call("get_telemetry_report")
        assert report["turret"]["streams"] == {"payload_camera": "idle"}
        forward = turret_with_camera.ctx.media.streams["payload_camera"]  # type: ignore[union-attr]
        # Not retried (10.10 off): the offline camera's stream fails and stays failed, so the
        # report cannot catch it between a retry's states.
        forward.set_retry(False)
        await a.call("start_stream", name="payload_camera")
        await wait_until(lambda: forward.state.value == "failed", timeout=15)
        report = await a.call("get_telemetry_report")
        assert report["turret"]["streams"] == {"payload_camera": "failed"}
        assert (await c.call("get_telemetry_report"))["turret"]["streams"] == {}
        assert "turret" not in await b.call("get_telemetry_report")
    finally:
        for conn in (a, b, c):
            await conn.close()


async def test_a_missing_or_vanished_line_is_reported_and_reopened(
    platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    link = tmp_path / "ttyTURRET"  # a stable name for the pty, as /dev/serial/by-id/... is
    daemon = await platform_factory(
        quiet_platform_config('payload.enabled=["turret"]', f"payload.turret_port={link}"),
        fleet_key,
    )
    conn = await station(daemon, fleet_key, "alpha")

    async def turret_report() -> dict[str, Any]:
        report: dict[str, Any] = (await conn.call("get_telemetry_report"))["turret"]
        return report

    simulators: list[TurretSimulator] = []
    try:
        # No device: no crash, the reason in telemetry and in a command's refusal.
        payload = next(a for a in daemon.ctx.supervisor.actors if a.name == "turret")
        await wait_until(lambda: "No such file" in getattr(payload, "error", ""))
        report = await turret_report()
        assert not report["connected"]
        assert report["error"].startswith(f"cannot open {link}")
        refused = await command(conn, 0, "az=10,el=0")
        assert not refused["accepted"]
        assert refused["reason"].startswith("turret line not open")
        # The microcontroller is plugged in: the line opens on the next retry.
        for round_ in range(2):
            simulators.append(TurretSimulator())
            simulators[-1].start()
            link.unlink(missing_ok=True)
            link.symlink_to(simulators[-1].path)
            await wait_until(lambda: getattr(payload, "driver", None) is not None, timeout=10)
            assert (await command(conn, 0, f"az={10 + round_},el=0"))["accepted"]
            assert (await turret_report())["error"] == ""
            # ...and unplugged: reported, then reopened when it is back.
            simulators[-1].close()
            await wait_until(lambda: "serial line closed" in getattr(payload, "error", ""))
        assert (await turret_report())["counters"]["acked"] >= 2  # kept across the lines
        assert daemon.ctx.supervisor.restarts.get("turret", 0) == 0  # never crashed
    finally:
        await conn.close()
        for simulator in simulators:
            simulator.close()
