"""The station's annunciator and link figures, driven by snapshots and an injected clock."""

from __future__ import annotations

import dataclasses

from brasidas.codecs.telemetry import TelemetryEncoder
from brasidas.codecs.telemetry_schema import (
    SCHEMA_VERSION,
    Admission,
    Attitude,
    Autonomy,
    Battery,
    Controller,
    Failsafe,
    Gps,
    Section,
    SectionValue,
    Snapshot,
    Streams,
    snapshot_to_wire,
)
from brasidas.config import TelemetryReceiverSection
from brasidas.messages import StationNotification
from stationd.telemetry import (
    CONNECTIONS_REFUSED,
    CONTROLLER_OVER_TEMPERATURE,
    GPS_FIX_LOST,
    LINK_DEGRADED,
    LINK_LOST,
    LOW_BATTERY,
    PATROL_HOLDING,
    SENSOR_STALE,
    STREAM_FAILED,
    Annunciator,
    LinkStats,
    TelemetryLink,
)

CONFIG = TelemetryReceiverSection()
SECTIONS: dict[type[Section], SectionValue] = {
    Battery: Battery(25.1, "high", True),
    Controller: Controller(True, (35.0, 38.0), (1.0, 1.2)),
    Gps: Gps(fix=True, lat=37.98, lon=23.72),
    Streams: Streams({"navcam": "playing"}),
}
HEALTHY = Snapshot(SECTIONS)


def with_(section: type[Section], value: SectionValue) -> Snapshot:
    return Snapshot({**SECTIONS, section: value})


def names(annunciator: Annunciator) -> set[str]:
    return set(annunciator.active)


def test_healthy_snapshot_raises_nothing() -> None:
    annunciator = Annunciator(CONFIG)
    assert annunciator.evaluate(HEALTHY, 0.0, 0.1, now=0.0) == []
    assert (
        annunciator.evaluate(Snapshot(), 0.0, None, now=0.0) == []
    )  # nothing known, nothing flagged


def test_low_battery_raises_names_the_voltage_and_clears_with_hysteresis() -> None:
    annunciator = Annunciator(CONFIG)
    (change,) = annunciator.evaluate(with_(Battery, Battery(22.6, "low")), 0, 0, 1.0)
    assert change.active
    assert change.warning.code == LOW_BATTERY
    assert change.warning.message == "low battery (22.6 V)"
    assert change.warning.since == 1.0
    # Recovering a little (under battery_clear_v) keeps the warning up: no flapping.
    assert annunciator.evaluate(with_(Battery, Battery(23.2, "medium")), 0, 0, 2) == []
    assert names(annunciator) == {"low_battery"}
    (change,) = annunciator.evaluate(with_(Battery, Battery(23.5, "medium")), 0, 0, 3)
    assert not change.active
    assert change.warning.name == "low_battery"
    # The platform's own LOW level raises it even without a voltage.
    (change,) = annunciator.evaluate(with_(Battery, Battery(None, "low")), 0, 0, 4)
    assert change.active
    assert change.warning.message == "low battery"


def test_controller_over_temperature_raises_and_clears_below_the_clear_threshold() -> None:
    annunciator = Annunciator(CONFIG)
    hot = Controller(True, (41.0, 72.4), (8.0, 9.0))
    (change,) = annunciator.evaluate(with_(Controller, hot), 0, 0, 1)
    assert change.active
    assert change.warning.code == CONTROLLER_OVER_TEMPERATURE
    assert change.warning.message == "controller over temperature (72 °C)"
    warm = dataclasses.replace(hot, temps_c=(41.0, 67.0))
    assert annunciator.evaluate(with_(Controller, warm), 0, 0, 2) == []
    cool = dataclasses.replace(hot, temps_c=(41.0, 60.0))
    (change,) = annunciator.evaluate(with_(Controller, cool), 0, 0, 3)
    assert not change.active


def test_gps_fix_lost_raises_and_clears() -> None:
    annunciator = Annunciator(CONFIG)
    (change,) = annunciator.evaluate(with_(Gps, Gps(fix=False, lost_for_s=3.0)), 0, 0, 1)
    assert change.active
    assert change.warning.code == GPS_FIX_LOST
    assert change.warning.message == "GPS fix lost (3 s ago)"
    # The figure changes: same warning, no new notification.
    assert annunciator.evaluate(with_(Gps, Gps(fix=False, lost_for_s=9.0)), 0, 0, 2) == []
    assert annunciator.active["gps_fix_lost"].message == "GPS fix lost (9 s ago)"
    assert annunciator.active["gps_fix_lost"].since == 1
    (change,) = annunciator.evaluate(HEALTHY, 0, 0, 3)
    assert not change.active
    assert change.warning.name == "gps_fix_lost"
    # A platform without a GPS (section null) is not "fix lost".
    assert annunciator.evaluate(with_(Gps, None), 0, 0, 4) == []


def test_link_degraded_by_silence_or_loss() -> None:
    annunciator = Annunciator(CONFIG)
    (change,) = annunciator.evaluate(HEALTHY, 0.0, silence=1.2, now=5)
    assert change.active
    assert change.warning.code == LINK_DEGRADED
    assert change.warning.message == "link degraded: telemetry silent for 1.2 s"
    (change,) = annunciator.evaluate(HEALTHY, 0.0, silence=0.1, now=6)
    assert not change.active
    (change,) = annunciator.evaluate(HEALTHY, 25.0, silence=0.1, now=7)
    assert change.active
    assert "25% of telemetry lost" in change.warning.message
    assert annunciator.evaluate(HEALTHY, 10.0, silence=0.1, now=8)[0].active is False


def test_each_failed_stream_is_named() -> None:
    annunciator = Annunciator(CONFIG)
    streams = {"navcam": "failed", "thermal": "error", "audio": "playing"}
    changes = annunciator.evaluate(with_(Streams, Streams(streams)), 0, 0, 1)
    assert {(c.warning.name, c.active) for c in changes} == {
        ("stream_failed:navcam", True),
        ("stream_failed:thermal", True),
    }
    assert all(c.warning.code == STREAM_FAILED for c in changes)
    assert annunciator.active["stream_failed:navcam"].message == "stream navcam failed"
    recovered = Streams({**streams, "navcam": "playing"})
    (change,) = annunciator.evaluate(with_(Streams, recovered), 0, 0, 2)
    assert (change.warning.name, change.active) == ("stream_failed:navcam", False)


def test_loss_over_a_sliding_window() -> None:
    stats = LinkStats(window=10)
    for seq in range(1, 11):
        stats.accepted(seq, now=seq * 0.2)
    assert stats.loss_pct == 0.0
    for seq in (12, 14, 16, 18, 20):  # every other one lost
        stats.accepted(seq, now=seq * 0.2)
    assert stats.loss_pct == 50.0
    for seq in range(21, 31):
        stats.accepted(seq, now=seq * 0.2)
    assert stats.loss_pct == 0.0
    assert stats.silence(now=6.5) == 0.5


def test_silence_counts_from_the_request_until_the_first_datagram() -> None:
    stats = LinkStats(window=10)
    assert stats.silence(now=3.0) is None
    stats.start(now=3.0)
    assert stats.silence(now=4.5) == 1.5


def test_link_announces_raise_and_clear_with_group_90_notifications() -> None:
    key = bytes(32)
    now = [100.0]
    notes: list[StationNotification] = []
    link = TelemetryLink(
        "rover-1", key, CONFIG, notes.append, clock=lambda: now[0], wall_clock=lambda: 1e9
    )
    link.stats.start(now[0])
    encoder = TelemetryEncoder("rover-1", key)
    assert link.feed(encoder.encode(snapshot_to_wire(SECTIONS), 1.0)[0])
    assert notes == []
    now[0] += 1.5  # silence
    link.tick()
    assert [(n.name, n.active, str(n.code)) for n in notes] == [("link_degraded", True, "90.13")]
    low = {**SECTIONS, Battery: Battery(22.0, "low")}
    assert link.feed(encoder.encode(snapshot_to_wire(low), 2.0)[0])
    assert [(n.name, n.active) for n in notes[1:]] == [
        ("link_degraded", False),
        ("low_battery", True),
    ]
    # Forged datagrams change nothing and are counted.
    forged = TelemetryEncoder("rover-1", bytes([1]) * 32).encode(snapshot_to_wire(SECTIONS), 3)[0]
    assert not link.feed(forged)
    assert link.decoder.rejected["forged"] == 1
    report = link.report()
    assert [w["name"] for w in report["warnings"]] == ["low_battery"]
    assert report["link"]["received"] == 2
    assert report["link"]["rejected_total"] == 1
    link.close()
    assert (notes[-1].name, notes[-1].active) == ("low_battery", False)
    assert notes[-1].as_dict()["code"] == "90.10"


def test_a_restarted_stream_far_ahead_starts_the_loss_figure_over() -> None:
    stats = LinkStats(window=10)
    for seq in range(1, 6):
        stats.accepted(seq, now=seq)
    stats.accepted(1_700_000_000_000, now=10)  # the platform's new encoder, clock-based
    assert stats.loss_pct == 0.0
    stats.accepted(1_700_000_000_002, now=10.2)
    assert stats.loss_pct == round(100 / 3, 1)


def test_a_stale_reading_raises_a_warning_until_a_fresh_one_arrives() -> None:
    annunciator = Annunciator(CONFIG)
    stale = Attitude(roll=1.0, pitch=0.0, yaw=0.0, age_ms=2500, stale=True)
    (change,) = annunciator.evaluate(with_(Attitude, stale), 0, 0, 1)
    assert change.active
    assert change.warning.code == SENSOR_STALE
    assert change.warning.message == "attitude stale (2 s old)"
    fresh = dataclasses.replace(stale, age_ms=40, stale=False)
    (change,) = annunciator.evaluate(with_(Attitude, fresh), 0, 0, 2)
    assert not change.active
    assert change.warning.name == "sensor_stale:attitude"


def test_a_platform_on_another_schema_is_named_not_shown_as_blanks() -> None:
    key = bytes(32)
    link = TelemetryLink("rover-1", key, CONFIG, lambda note: None, clock=lambda: 5.0)
    datagram = bytearray(TelemetryEncoder("rover-1", None).encode({"mode": "teleop"}, 1.0)[0])
    datagram[0] = SCHEMA_VERSION - 1  # an older platform's first byte
    assert not link.feed(bytes(datagram))
    error = link.report()["link"]["error"]
    assert error == (
        f"the platform sends telemetry schema v{SCHEMA_VERSION - 1}; "
        f"this station reads v{SCHEMA_VERSION} (update the older of the two)"
    )
    assert link.decoder.rejected["version"] == 1
    # Once datagrams of our schema arrive (the platform was updated), the message goes.
    assert link.feed(TelemetryEncoder("rover-1", key).encode(snapshot_to_wire(SECTIONS), 2.0)[0])
    assert link.report()["link"]["error"] == ""


def test_a_holding_patrol_raises_with_its_reason_and_clears() -> None:
    annunciator = Annunciator(CONFIG)
    holding = Autonomy(state="holding", reason="GPS fix lost or stale (2.4 s old)")
    (change,) = annunciator.evaluate(with_(Autonomy, holding), 0.0, 0.1, now=1.0)
    assert change.active
    assert change.warning.code == PATROL_HOLDING
    assert change.warning.message == "patrol holding: GPS fix lost or stale (2.4 s old)"
    patrolling = Autonomy(state="patrolling")
    (change,) = annunciator.evaluate(with_(Autonomy, patrolling), 0.0, 0.1, now=2.0)
    assert not change.active
    assert names(annunciator) == set()


def test_failsafe_hold_raises_link_lost_until_the_operator_re_engages() -> None:
    annunciator = Annunciator(CONFIG)
    held = Failsafe("hold", "no heartbeat from st-1 for 1.5 s: holding", "st-1")
    (change,) = annunciator.evaluate(with_(Failsafe, held), 0, 0, 1.0)
    assert change.active
    assert change.warning.code == LINK_LOST
    assert change.warning.message.startswith("LINK LOST: platform hold")
    assert annunciator.evaluate(with_(Failsafe, Failsafe("normal", "", "st-1")), 0, 0, 2) == [
        dataclasses.replace(change, active=False)
    ]


def test_connections_refused_at_a_high_rate_raise_90_24_and_clear() -> None:
    annunciator = Annunciator(dataclasses.replace(CONFIG, refused_warn=100))
    few = Admission({"evicted_host": 99}, 8, "10.0.0.9", 99, 10.0)
    assert annunciator.evaluate(with_(Admission, few), 0.0, 0.1, now=0.0) == []
    many = Admission({"evicted_host": 340}, 8, "10.0.0.9", 340, 10.0)
    (change,) = annunciator.evaluate(with_(Admission, many), 0.0, 0.1, now=1.0)
    assert change.active
    assert change.warning.code == CONNECTIONS_REFUSED
    assert str(CONNECTIONS_REFUSED) == "90.24"
    assert change.warning.message == "connections refused from 10.0.0.9: 340 in 10 s"
    # The window moved on: the counters since start stay, the warning clears.
    quiet = Admission({"evicted_host": 340}, 0, "", 0, 0.0)
    (cleared,) = annunciator.evaluate(with_(Admission, quiet), 0.0, 0.1, now=12.0)
    assert not cleared.active
    assert names(annunciator) == set()
