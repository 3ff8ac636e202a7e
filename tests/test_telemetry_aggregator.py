"""The platform's telemetry aggregator: sections from bus messages, health, system figures."""

from __future__ import annotations

from pathlib import Path

import pytest
from conftest import quiet_platform_config

from brasidas import topics
from brasidas.actor import Supervisor
from brasidas.bus import Bus
from brasidas.codecs.jsonrpc import Dispatcher
from brasidas.codecs.telemetry_schema import (
    Battery,
    Computer,
    Controller,
    Diagnostics,
    Gps,
    Override,
    SectionError,
    Streams,
    snapshot_to_json,
)
from brasidas.messages import (
    ControllerStatus,
    GpsFix,
    GpsFixLost,
    OverrideState,
    PlatformHealth,
    StreamStatus,
)
from brasidas.status import Battery as Level
from platformd.context import PlatformContext
from platformd.telemetry import (
    TelemetryAggregator,
    allowed_host,
    cpu_temperature,
    system_info,
)


def controller(
    connected: bool, volts: float | None, *, monitor: bool = True, amps: float = 0.0
) -> ControllerStatus:
    return ControllerStatus(connected, volts, monitor, (25.0, 25.0), (amps, amps))


FIX = GpsFix(37.98380961, 23.72753882, 95.0, 0.0, None, 1, 9, 0.9, "12:00:00.000Z")


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def make(clock: Clock, *overrides: str) -> tuple[TelemetryAggregator, Bus]:
    bus = Bus()
    ctx = PlatformContext(
        config=quiet_platform_config(*overrides),
        bus=bus,
        supervisor=Supervisor(),
        rpc=Dispatcher(),
        fleet_key=None,
    )
    aggregator = TelemetryAggregator(ctx, clock=clock, monotonic=clock)
    aggregator.register()
    return aggregator, bus


def test_sections_follow_the_bus() -> None:
    clock = Clock()
    aggregator, bus = make(clock, "motor.enabled=true")
    aggregator.subscribe_reports()
    health: list[PlatformHealth] = []
    bus.subscribe(topics.PLATFORM_HEALTH, health.append)

    empty = aggregator.snapshot()
    assert empty[Battery] is None
    assert empty[Gps] is None
    assert empty[Controller] is None
    assert empty[Override] == Override("autonomous", False, None)
    assert empty[Streams] == Streams({})

    bus.publish(topics.OVERRIDE_STATE, OverrideState(True, "s1", "station-9"))
    bus.publish(
        topics.CONTROLLER_STATUS,
        ControllerStatus(True, 22.512, True, (41.26, 39.0), (3.04, 2.5), 12.251, stamp=clock.now),
    )
    clock.now += 0.25
    snap = aggregator.snapshot()
    assert snap[Override] == Override("teleop", True, "station-9")
    assert snap[Battery] == Battery(22.51, "low", True, age_ms=250, stale=False)
    assert snap[Controller] == Controller(
        True, (41.3, 39.0), (3.0, 2.5), 12.25, age_ms=250, stale=False
    )
    assert health[-1].battery is Level.LOW
    assert health[-1].controller
    assert not health[-1].fault

    bus.publish(topics.GPS_FIX, FIX)
    gps = aggregator.snapshot()[Gps]
    assert isinstance(gps, Gps)
    assert gps.fix is True
    assert gps.lat == 37.9838096
    assert gps.sats == 9
    assert health[-1].gps_fix is True
    bus.publish(topics.GPS_FIX_LOST, GpsFixLost("receiver silent"))
    clock.now += 4
    gps = aggregator.snapshot()[Gps]
    assert isinstance(gps, Gps)
    assert gps.fix is False
    assert gps.lost_for_s == 4.0
    assert gps.lat == 37.9838096
    assert health[-1].gps_fix is False

    # Streams the media service has but that never changed state are listed as they are.
    class Media:
        def describe_streams(self) -> list[dict[str, str]]:
            return [{"name": "navcam", "state": "idle"}, {"name": "audio_out", "state": "idle"}]

    aggregator.ctx.media = Media()  # type: ignore[assignment]
    assert aggregator.snapshot()[Streams] == Streams({"navcam": "idle", "audio_out": "idle"})
    bus.publish(topics.STREAM_STATES, StreamStatus("navcam", "video_out", "playing"))
    assert health[-1].streaming is True
    bus.publish(topics.STREAM_STATES, StreamStatus("navcam", "video_out", "failed", "no camera"))
    assert aggregator.snapshot()[Streams] == Streams({"navcam": "failed", "audio_out": "idle"})
    assert health[-1].fault
    assert health[-1].faults == ("stream:navcam",)
    bus.publish(topics.CONTROLLER_STATUS, controller(False, None))
    assert health[-1].faults == ("controller", "stream:navcam")
    assert not health[-1].controller
    assert health[-1].battery is Level.UNKNOWN
    # Only changes are published.
    count = len(health)
    bus.publish(topics.CONTROLLER_STATUS, controller(False, None))
    assert len(health) == count
    assert bus.last(topics.PLATFORM_HEALTH) == health[-1]


def test_readings_carry_their_age_and_turn_stale_after_a_few_periods() -> None:
    clock = Clock()
    # Polls at 2 Hz: stale after max(1 s, 3 periods) = 1.5 s.
    aggregator, bus = make(clock, "motor.poll_hz=2")
    bus.publish(
        topics.CONTROLLER_STATUS,
        ControllerStatus(True, 24.0, True, (30.0, 30.0), (1.0, 1.0), stamp=clock.now),
    )
    clock.now += 1.4
    battery = aggregator.battery_section()
    assert battery is not None
    assert battery.age_ms == 1400
    assert not battery.stale
    clock.now += 0.2
    battery = aggregator.battery_section()
    assert battery is not None
    assert battery.age_ms == 1600
    assert battery.stale
    ctl = aggregator.controller_section()
    assert ctl is not None
    assert ctl.stale
    # A status without readings (not polled yet) has no age and is not stale.
    bus.publish(topics.CONTROLLER_STATUS, ControllerStatus(False, stamp=clock.now - 60))
    ctl = aggregator.controller_section()
    assert ctl is not None
    assert ctl.age_ms is None
    assert not ctl.stale


def test_battery_levels_follow_the_configured_thresholds() -> None:
    aggregator, bus = make(Clock(), "telemetry.battery_low_v=11.5", "telemetry.battery_high_v=12.4")
    aggregator.subscribe_reports()
    levels = []
    for volts in (11.0, 11.5, 12.39, 12.4, 13.0):
        bus.publish(topics.CONTROLLER_STATUS, controller(True, volts))
        battery = aggregator.snapshot()[Battery]
        assert isinstance(battery, Battery)
        levels.append(battery.level)
    assert levels == ["low", "medium", "medium", "high", "high"]


def test_diagnostics_section_only_when_switched_on() -> None:
    aggregator, _ = make(Clock())
    assert aggregator.snapshot()[Diagnostics] is None
    aggregator.diagnostics = True
    diagnostics = aggregator.snapshot()[Diagnostics]
    assert isinstance(diagnostics, Diagnostics)
    assert diagnostics.telemetry["snapshots"] == 2
    assert diagnostics.actor_restarts == {}


def test_a_failing_section_is_that_sections_error_and_the_rest_goes_on(
    caplog: pytest.LogCaptureFixture,
) -> None:
    aggregator, bus = make(Clock())

    def broken() -> Computer:
        raise ZeroDivisionError("division by zero")

    aggregator.ctx.telemetry._sources[Computer] = broken
    bus.publish(topics.CONTROLLER_STATUS, controller(True, 25.5))
    for _ in range(3):
        snap = aggregator.snapshot()
    assert snap[Computer] == SectionError("ZeroDivisionError: division by zero")
    assert isinstance(snap[Battery], Battery)
    assert snapshot_to_json(snap)["computer"] == {"error": "ZeroDivisionError: division by zero"}
    # Counted every time, logged once (with the traceback).
    assert aggregator.ctx.telemetry.errors == {"computer": 3}
    logged = [r for r in caplog.records if "section computer failed" in r.getMessage()]
    assert len(logged) == 1
    assert logged[0].exc_info is not None
    aggregator.diagnostics = True
    diagnostics = aggregator.snapshot()[Diagnostics]
    assert isinstance(diagnostics, Diagnostics)
    assert diagnostics.section_errors == {"computer": 4}


def test_one_source_per_section() -> None:
    aggregator, _ = make(Clock())
    with pytest.raises(ValueError, match="battery"):
        aggregator.ctx.telemetry.register(Battery, aggregator.battery_section)


def test_battery_level_follows_the_monitor_flag() -> None:
    aggregator, bus = make(Clock())
    aggregator.subscribe_reports()
    bus.publish(topics.CONTROLLER_STATUS, controller(True, 22.0, monitor=True))
    battery = aggregator.battery_section()
    assert battery is not None
    assert (battery.volts, battery.level) == (22.0, "low")
    bus.publish(topics.CONTROLLER_STATUS, controller(True, 22.0, monitor=False))
    battery = aggregator.battery_section()
    assert battery is not None
    assert (battery.level, battery.monitor) == (None, False)
    health = bus.last(topics.PLATFORM_HEALTH)
    assert health is not None
    assert health.battery is Level.UNKNOWN


def test_cpu_temperature_prefers_the_cpu_zone(tmp_path: Path) -> None:
    assert cpu_temperature(tmp_path / "absent") is None
    assert cpu_temperature(tmp_path) is None
    for index, (kind, millis) in enumerate([("acpitz", "40000"), ("x86_pkg_temp", "52125")]):
        zone = tmp_path / f"thermal_zone{index}"
        zone.mkdir()
        (zone / "type").write_text(kind + "\n")
        (zone / "temp").write_text(millis + "\n")
    assert cpu_temperature(tmp_path) == 52.1
    (tmp_path / "thermal_zone1" / "temp").write_text("garbage")
    assert cpu_temperature(tmp_path) is None


def test_system_info_reads_meminfo(tmp_path: Path) -> None:
    meminfo = tmp_path / "meminfo"
    meminfo.write_text("MemTotal:  2048000 kB\nMemFree: 100 kB\nMemAvailable:   1024000 kB\n")
    info = system_info(tmp_path, meminfo)
    assert info["mem_free_mb"] == 1000.0
    assert info["mem_total_mb"] == 2000.0
    assert info["cpu_temp_c"] is None
    assert len(info["load"]) == 3
    assert system_info(tmp_path, tmp_path / "none")["mem_free_mb"] is None


def test_only_loopback_or_the_callers_host_may_receive() -> None:
    assert allowed_host("127.0.0.1", "10.0.0.5")
    assert allowed_host("127.3.0.1", "10.0.0.5")
    assert allowed_host("10.0.0.5", "10.0.0.5")
    assert allowed_host("10.0.0.5", "::ffff:10.0.0.5")
    assert not allowed_host("10.0.0.6", "10.0.0.5")
    assert not allowed_host("255.255.255.255", "10.0.0.5")
    assert not allowed_host("example.org", "10.0.0.5")
