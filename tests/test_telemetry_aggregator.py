"""The platform's telemetry aggregator: sections from bus messages, health, system figures."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import pytest
from conftest import quiet_platform_config

from brasidas import topics
from brasidas.actor import Supervisor
from brasidas.bus import Bus, Topic
from brasidas.codecs.jsonrpc import Dispatcher
from brasidas.messages import OverrideState, PlatformHealth
from brasidas.status import Battery
from platformd.context import PlatformContext
from platformd.telemetry import (
    WATCHED,
    TelemetryAggregator,
    allowed_host,
    cpu_temperature,
    system_info,
    to_plain,
)


@dataclass(frozen=True)
class FakeControllerStatus:
    connected: bool
    battery_volts: float | None
    heatsink_c: tuple[float, float]
    motor_amps: tuple[float, float]


@dataclass(frozen=True)
class FakeFix:
    latitude: float
    longitude: float
    satellites: int
    extra: dict[str, float] = field(default_factory=dict)


class Clock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def fake_topics(monkeypatch: pytest.MonkeyPatch) -> dict[str, Topic[object]]:
    """Stand-ins for topics other subsystems declare, under the names the aggregator looks for."""
    made: dict[str, Topic[object]] = {}
    for name in ("CONTROLLER_STATUS", "GPS_FIX", "GPS_FIX_LOST", "STREAM_STATES", "IMU_STATUS"):
        if getattr(topics, name, None) is None:
            made[name] = Topic(name.lower(), retain=True)
            monkeypatch.setattr(topics, name, made[name], raising=False)
        else:
            made[name] = getattr(topics, name)
    return made


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


def test_sections_follow_the_bus(fake_topics: dict[str, Topic[object]]) -> None:
    clock = Clock()
    aggregator, bus = make(clock, "motor.enabled=true")
    assert {"controller", "gps_fix", "gps_lost", "streams", "imu"} <= set(aggregator.wire())
    health: list[PlatformHealth] = []
    bus.subscribe(topics.PLATFORM_HEALTH, health.append)

    empty = aggregator.snapshot()
    assert empty["battery"] is None and empty["gps"] is None and empty["controller"] is None
    assert empty["mode"] == "autonomous" and empty["streams"] == {}

    bus.publish(topics.OVERRIDE_STATE, OverrideState(True, "s1", "station-9"))
    bus.publish(
        fake_topics["CONTROLLER_STATUS"],
        FakeControllerStatus(True, 22.512, (41.26, 39.0), (3.04, 2.5)),
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
        "internal_volts": None,
    }
    assert health[-1].battery is Battery.LOW and health[-1].controller and not health[-1].fault

    bus.publish(fake_topics["GPS_FIX"], FakeFix(37.98380961, 23.72753882, 9))
    assert aggregator.snapshot()["gps"]["fix"] is True
    assert aggregator.snapshot()["gps"]["latitude"] == 37.9838096
    assert health[-1].gps_fix is True
    bus.publish(fake_topics["GPS_FIX_LOST"], object())
    clock.now += 4
    gps = aggregator.snapshot()["gps"]
    assert gps["fix"] is False and gps["lost_for_s"] == 4.0 and gps["latitude"] == 37.9838096
    assert health[-1].gps_fix is False

    # Streams the media service has but that never changed state are listed as they are.
    aggregator.ctx.capabilities["streams"] = lambda: [
        {"name": "navcam", "state": "idle"},
        {"name": "audio_out", "state": "idle"},
    ]
    assert aggregator.snapshot()["streams"] == {"navcam": "idle", "audio_out": "idle"}
    bus.publish(fake_topics["STREAM_STATES"], {"name": "navcam", "state": "playing"})
    assert health[-1].streaming is True
    bus.publish(fake_topics["STREAM_STATES"], {"name": "navcam", "state": "failed"})
    assert aggregator.snapshot()["streams"] == {"navcam": "failed", "audio_out": "idle"}
    assert health[-1].fault and health[-1].faults == ("stream:navcam",)
    bus.publish(fake_topics["CONTROLLER_STATUS"], FakeControllerStatus(False, None, (0, 0), (0, 0)))
    assert health[-1].faults == ("controller", "stream:navcam") and not health[-1].controller
    assert health[-1].battery is Battery.UNKNOWN
    # Only changes are published.
    count = len(health)
    bus.publish(fake_topics["CONTROLLER_STATUS"], FakeControllerStatus(False, None, (0, 0), (0, 0)))
    assert len(health) == count
    assert bus.last(topics.PLATFORM_HEALTH) == health[-1]


def test_battery_levels_follow_the_configured_thresholds(
    fake_topics: dict[str, Topic[object]],
) -> None:
    aggregator, bus = make(Clock(), "telemetry.battery_low_v=11.5", "telemetry.battery_high_v=12.4")
    aggregator.wire()
    levels = []
    for volts in (11.0, 11.5, 12.39, 12.4, 13.0):
        bus.publish(
            fake_topics["CONTROLLER_STATUS"], FakeControllerStatus(True, volts, (25, 25), (0, 0))
        )
        levels.append(aggregator.snapshot()["battery"]["level"])
    assert levels == ["low", "medium", "medium", "high", "high"]


def test_diagnostics_section_only_when_switched_on() -> None:
    aggregator, _ = make(Clock())
    assert aggregator.snapshot()["diagnostics"] is None
    aggregator.diagnostics = True
    diagnostics = aggregator.snapshot()["diagnostics"]
    assert diagnostics["telemetry"]["snapshots"] == 2 and diagnostics["actor_restarts"] == {}


def test_every_watched_topic_that_exists_is_a_topic() -> None:
    for names in WATCHED.values():
        for name in names:
            value = getattr(topics, name, None)
            assert value is None or isinstance(value, Topic), name


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
    plain = to_plain(FakeFix(1.123456789, 2.0, 3, {"x": 0.5}))
    assert plain == {"latitude": 1.1234568, "longitude": 2.0, "satellites": 3, "extra": {"x": 0.5}}
    assert to_plain((Battery.LOW, None)) == [1, None]


@dataclass(frozen=True)
class FakeMonitoredStatus(FakeControllerStatus):
    battery_monitor: bool = True


def test_battery_level_follows_the_monitor_flag(fake_topics: dict[str, Topic[object]]) -> None:
    aggregator, bus = make(Clock())
    aggregator.wire()
    topic = fake_topics["CONTROLLER_STATUS"]
    bus.publish(topic, FakeMonitoredStatus(True, 22.0, (25, 25), (0, 0), battery_monitor=True))
    assert aggregator.snapshot()["battery"] == {"volts": 22.0, "level": "low", "monitor": True}
    bus.publish(topic, FakeMonitoredStatus(True, 22.0, (25, 25), (0, 0), battery_monitor=False))
    assert aggregator.snapshot()["battery"] == {"volts": 22.0, "level": None, "monitor": False}
    assert bus.last(topics.PLATFORM_HEALTH).battery is Battery.UNKNOWN
    # Without a flag in the status, the configured default decides.
    quiet, bus = make(Clock(), "telemetry.battery_monitor=false")
    quiet.wire()
    bus.publish(topic, FakeControllerStatus(True, 22.0, (25, 25), (0, 0)))
    assert quiet.snapshot()["battery"]["level"] is None
