"""The one snapshot -> channel messages projection (issue 32): pure, no I/O, time passed in.
Foxglove live and the recorder both log what it returns."""

from __future__ import annotations

import json

from brasidas.codecs.telemetry import TelemetryEncoder
from brasidas.codecs.telemetry_schema import (
    Autonomy,
    Failsafe,
    Gps,
    Lights,
    Motion,
    Override,
    Pose,
    Section,
    Snapshot,
    Streams,
    snapshot_to_wire,
)
from brasidas.config import TelemetryReceiverSection
from brasidas.messages import TelemetrySnapshot
from brasidas.recording import schemas
from brasidas.recording.projection import ChannelMessage, StateChange, channel_messages
from stationd.telemetry.link import TelemetryLink

T = 1_700_000_000_000_000_000


def _snapshot(*values: Section) -> Snapshot:
    return Snapshot({type(value): value for value in values})


def _topics(messages: list[ChannelMessage]) -> list[str]:
    return [m.spec.topic for m in messages]


def test_the_first_snapshot_gives_every_section_its_channel_and_what_it_feeds() -> None:
    now = _snapshot(
        Gps(fix=True, lat=48.0, lon=11.0, alt=500.0, hdop=0.8),
        Pose(lat=48.1, lon=11.1, sigma_m=0.4),
        Motion(mode="teleop", linear=0.5, angular=-0.2),
        Autonomy(state="patrolling", path=((48.0, 11.0), (48.1, 11.1))),
        Lights(main=True),
    )
    messages, changes = channel_messages(None, now, T)
    topics = _topics(messages)
    for cls in (Gps, Pose, Motion, Autonomy, Lights):
        assert schemas.telemetry_channel(cls).topic in topics
    assert schemas.GPS.topic in topics
    assert schemas.POSE.topic in topics
    assert schemas.MOTOR_COMMAND.topic in topics
    assert schemas.TELEOP_VELOCITY.topic in topics
    assert schemas.AUTONOMY_VELOCITY.topic not in topics
    route = next(m for m in messages if m.spec is schemas.ROUTE)
    line = json.loads(json.loads(route.data)["geojson"])["features"][0]["geometry"]
    assert line["coordinates"] == [[11.0, 48.0], [11.1, 48.1]]
    motion = next(m for m in messages if m.spec is schemas.MOTOR_COMMAND)
    assert json.loads(motion.data) == {"linear": 0.5, "angular": -0.2}
    gps = next(m for m in messages if m.spec is schemas.GPS)
    assert json.loads(gps.data)["position_covariance"][0] == (0.8 * 2.5) ** 2
    assert all(m.time_ns == T for m in messages)
    assert changes == [StateChange("patrol", "patrolling")]


def test_a_gps_without_a_fix_feeds_no_position() -> None:
    messages, _ = channel_messages(None, _snapshot(Gps(fix=False, lat=48.0, lon=11.0)), T)
    assert _topics(messages) == [schemas.telemetry_channel(Gps).topic]


def test_an_unchanged_section_is_left_out_unless_asked_again() -> None:
    before = _snapshot(Lights(main=True), Motion(linear=0.3))
    now = _snapshot(Lights(main=True), Motion(linear=0.4))
    messages, _ = channel_messages(before, now, T)
    assert schemas.telemetry_channel(Lights).topic not in _topics(messages)
    assert schemas.telemetry_channel(Motion).topic in _topics(messages)
    again, _ = channel_messages(before, now, T, again=frozenset({Lights}))
    assert schemas.telemetry_channel(Lights).topic in _topics(again)


def test_state_records_are_the_ones_that_changed() -> None:
    before = _snapshot(
        Failsafe(step="normal", controller="gcs-1"),
        Override(engaged=False),
        Streams(states={"navcam": "streaming", "audio": "idle"}),
    )
    now = _snapshot(
        Failsafe(step="stopped", reason="link lost", controller="gcs-1"),
        Override(engaged=True, station="gcs-2"),
        Streams(states={"navcam": "failed", "audio": "idle"}),
    )
    _, changes = channel_messages(before, now, T)
    assert changes == [
        StateChange("failsafe", "stopped", None, "link lost"),
        StateChange("override", "engaged", "gcs-2"),
        StateChange("stream:navcam", "failed"),
    ]
    _, released = channel_messages(now, _snapshot(Failsafe(step="stopped", reason="link lost")), T)
    assert released == [StateChange("control", "free")]
    assert json.loads(released[0].encode()) == {
        "what": "control",
        "state": "free",
        "station": None,
        "reason": "",
    }


def test_the_link_hands_over_a_copy_of_its_snapshot_after_each_datagram() -> None:
    seen: list[TelemetrySnapshot] = []
    key = bytes(32)
    link = TelemetryLink(
        "rover-1",
        key,
        TelemetryReceiverSection(),
        lambda note: None,
        clock=lambda: 5.0,
        wall_clock=lambda: 7.0,
        on_snapshot=seen.append,
    )
    encoder = TelemetryEncoder("rover-1", key)
    assert link.feed(encoder.encode(snapshot_to_wire({Lights: Lights(main=True)}), 1.0)[0])
    assert link.feed(encoder.encode(snapshot_to_wire({Motion: Motion(linear=0.2)}), 2.0)[0])
    forged = TelemetryEncoder("rover-1", bytes([1]) * 32).encode(snapshot_to_wire({}), 3.0)[0]
    assert not link.feed(forged)
    assert [s.platform_id for s in seen] == ["rover-1", "rover-1"]
    assert seen[1].time_ns == 7_000_000_000
    # Merged (datagrams carry subsets), and the first is not changed by the second datagram.
    assert seen[0].snapshot.get(Motion) is None
    assert seen[1].snapshot.get(Lights) == Lights(main=True)
    assert seen[1].snapshot.get(Motion) == Motion(linear=0.2)
