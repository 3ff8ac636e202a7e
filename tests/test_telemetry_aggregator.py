"""The platform's telemetry aggregator: sections from bus messages, health, system figures."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from conftest import quiet_platform_config

from brasidas import topics
from brasidas.actor import Supervisor
from brasidas.bus import Bus
from brasidas.codecs.jsonrpc import Dispatcher
from brasidas.messages import (
    ControllerStatus,
    GpsFix,
    GpsFixLost,
    OverrideState,
    PlatformHealth,
    StreamStatus,
)
from brasidas.status import Battery
from platformd.context import PlatformContext
from platformd.telemetry import (
    TelemetryAggregator,
    allowed_host,
    cpu_temperature,
    system_info,
    to_plain,
)


@dataclass(frozen=True)
class Sample:
    latitude: float
    longitude: float
    satellites: int
    extra: dict[str, float] = field(default_factory=dict)


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
    aggregator = TelemetryAggregator(ctx, clock=clock)
    ctx.telemetry_sources.update(aggregator.sources())
    return aggregator, bus


def test_sections_follow_the_bus() -> None:
    clock = Clock()
    aggregator, bus = make(clock, "motor.enabled=true")
    aggregator.subscribe_reports()
    health: list[PlatformHealth] = []
    bus.subscribe(topics.PLATFORM_HEALTH, health.append)

    empty = aggregator.snapshot()
    assert empty["battery"] is None and empty["gps"] is None and empty["controller"] is None
    assert empty["mode"] == "autonomous" and empty["streams"] == {}

    bus.publish(topics.OVERRIDE_STATE, OverrideState(True, "s1", "station-9"))
    bus.publish(
        topics.CONTROLLER_STATUS,
        ControllerStatus(True, 22.512, True, (41.26, 39.0), (3.04, 2.5), 12.251),
    )
    snap = aggregator.snapshot()
    assert snap["mode"] == "teleop" and snap["override"] == {
        "engaged": True,
        "station": "station-9",
    }
    assert snap["battery"] == {"volts": 22.51, "level": "low", "monitor": True}
    assert snap["controller"] == {
        "connected": True,
        "temps_c": [41.3, 39.0],
        "amps": [3.0, 2.5],
        "internal_volts": 12.25,
    }
    assert health[-1].battery is Battery.LOW and health[-1].controller and not health[-1].fault

    bus.publish(topics.GPS_FIX, FIX)
    assert aggregator.snapshot()["gps"]["fix"] is True
    assert aggregator.snapshot()["gps"]["lat"] == 37.9838096
    assert health[-1].gps_fix is True
    bus.publish(topics.GPS_FIX_LOST, GpsFixLost("receiver silent"))
    clock.now += 4
    gps = aggregator.snapshot()["gps"]
    assert gps["fix"] is False and gps["lost_for_s"] == 4.0 and gps["lat"] == 37.9838096
    assert health[-1].gps_fix is False

    # Streams the media service has but that never changed state are listed as they are.
    aggregator.ctx.capabilities["streams"] = lambda: [
        {"name": "navcam", "state": "idle"},
        {"name": "audio_out", "state": "idle"},
    ]
    assert aggregator.snapshot()["streams"] == {"navcam": "idle", "audio_out": "idle"}
    bus.publish(topics.STREAM_STATES, StreamStatus("navcam", "video_out", "playing"))
    assert health[-1].streaming is True
    bus.publish(topics.STREAM_STATES, StreamStatus("navcam", "video_out", "failed", "no camera"))
    assert aggregator.snapshot()["streams"] == {"navcam": "failed", "audio_out": "idle"}
    assert health[-1].fault and health[-1].faults == ("stream:navcam",)
    bus.publish(topics.CONTROLLER_STATUS, controller(False, None))
    assert health[-1].faults == ("controller", "stream:navcam") and not health[-1].controller
    assert health[-1].battery is Battery.UNKNOWN
    # Only changes are published.
    count = len(health)
    bus.publish(topics.CONTROLLER_STATUS, controller(False, None))
    assert len(health) == count
    assert bus.last(topics.PLATFORM_HEALTH) == health[-1]


def test_battery_levels_follow_the_configured_thresholds() -> None:
    aggregator, bus = make(Clock(), "telemetry.battery_low_v=11.5", "telemetry.battery_high_v=12.4")
    aggregator.subscribe_reports()
    levels = []
    for volts in (11.0, 11.5, 12.39, 12.4, 13.0):
        bus.publish(topics.CONTROLLER_STATUS, controller(True, volts))
        levels.append(aggregator.snapshot()["battery"]["level"])
    assert levels == ["low", "medium", "medium", "high", "high"]


def test_diagnostics_section_only_when_switched_on() -> None:
    aggregator, _ = make(Clock())
    assert aggregator.snapshot()["diagnostics"] is None
    aggregator.diagnostics = True
    diagnostics = aggregator.snapshot()["diagnostics"]
    assert diagnostics["telemetry"]["snapshots"] == 2 and diagnostics["actor_restarts"] == {}


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
    assert info["mem_free_mb"] == 1000.0 and info["mem_total_mb"] == 2000.0
    assert info["cpu_temp_c"] is None and len(info["load"]) == 3
    assert system_info(tmp_path, tmp_path / "none")["mem_free_mb"] is None


def test_only_loopback_or_the_callers_host_may_receive() -> None:
    assert allowed_host("127.0.0.1", "10.0.0.5")
    assert allowed_host("127.3.0.1", "10.0.0.5")
    assert allowed_host("10.0.0.5", "10.0.0.5")
    assert allowed_host("10.0.0.5", "::ffff:10.0.0.5")
    assert not allowed_host("10.0.0.6", "10.0.0.5")
    assert not allowed_host("255.255.255.255", "10.0.0.5")
    assert not allowed_host("example.org", "10.0.0.5")


def test_to_plain_handles_enums_tuples_and_nested_dataclasses() -> None:
    plain = to_plain(Sample(1.123456789, 2.0, 3, {"x": 0.5}))
    assert plain == {"latitude": 1.1234568, "longitude": 2.0, "satellites": 3, "extra": {"x": 0.5}}
    assert to_plain((Battery.LOW, None)) == [1, None]


def test_battery_level_follows_the_monitor_flag() -> None:
    aggregator, bus = make(Clock())
    aggregator.subscribe_reports()
    bus.publish(topics.CONTROLLER_STATUS, controller(True, 22.0, monitor=True))
    assert aggregator.snapshot()["battery"] == {"volts": 22.0, "level": "low", "monitor": True}
    bus.publish(topics.CONTROLLER_STATUS, controller(True, 22.0, monitor=False))
    assert aggregator.snapshot()["battery"] == {"volts": 22.0, "level": None, "monitor": False}
    assert bus.last(topics.PLATFORM_HEALTH).battery is Battery.UNKNOWN
