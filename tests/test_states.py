"""Connection-like state as explicit enums (brasidas.states): MAVLink links, uploads,
admission slots and the planner process take only the transitions their tables allow, and
each reaches the states the protocol says it does."""

from __future__ import annotations

import asyncio
import enum
import hashlib
import os
import signal
from typing import Any

import pytest
from conftest import wait_until
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas.admission import AdmissionLimits, AdmissionPolicy, SlotState
from brasidas.states import InvalidTransition, Transitions
from platformd.autonomy.planner_client import PlannerProcess, PlannerState
from platformd.mavlink.link import LinkState, UploadState
from platformd.mavlink.mission_protocol import UPLOAD_RETRIES, UPLOAD_RETRY_S
from platformd.mavlink.vehicle import MavlinkVehicle, UploadItems

GCS = ("192.0.2.20", 14550)
TARGET = ("192.0.2.1", 14550)
KEY = hashlib.sha256(b"states").digest()


class Light(enum.Enum):
    RED = 1
    GREEN = 2
    OFF = 3


LIGHTS = Transitions[Light](
    "light", {Light.RED: frozenset((Light.GREEN, Light.OFF)), Light.GREEN: frozenset((Light.RED,))}
)


def test_a_transition_not_in_the_table_is_refused_naming_both_states() -> None:
    assert LIGHTS.check(Light.RED, Light.GREEN) is Light.GREEN
    with pytest.raises(InvalidTransition, match="light: GREEN → OFF is not allowed"):
        LIGHTS.check(Light.GREEN, Light.OFF)
    with pytest.raises(InvalidTransition):
        LIGHTS.check(Light.OFF, Light.RED)  # not in the table: final
    assert LIGHTS.final(Light.OFF)
    assert not LIGHTS.final(Light.RED)


class Station:
    """A ground station's pymavlink encoder, signed with ``key`` if given."""

    def __init__(self, key: bytes | None = None) -> None:
        self.mav = mavlink.MAVLink(None, 255, 190)
        if key is not None:
            self.mav.signing.secret_key = key
            self.mav.signing.sign_outgoing = True
            self.mav.signing.link_id = 1
            self.mav.signing.timestamp = 10**12

    def frame(self, message: Any) -> bytes:
        data = bytes(message.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        return data


def heartbeat() -> Any:
    return mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, 8, 0, 0, 0, 3)


def test_a_link_is_a_stranger_until_trusted_then_forgotten_when_silent() -> None:
    vehicle = MavlinkVehicle(1, targets=(TARGET,), key=KEY, link_timeout=5.0)
    assert vehicle.links[TARGET].state is LinkState.CONFIGURED
    vehicle.feed(Station().frame(heartbeat()), GCS, 0.0)  # unsigned: watches, commands nothing
    link = vehicle.links[GCS]
    assert link.state is LinkState.STRANGER
    assert link.stranger
    vehicle.feed(Station(KEY).frame(heartbeat()), GCS, 1.0)
    assert link.state is LinkState.TRUSTED
    assert not link.stranger
    vehicle.tick(7.0)
    assert GCS not in vehicle.links
    assert link.state is LinkState.FORGOTTEN
    # A configured target is never forgotten, however long it is silent.
    assert vehicle.links[TARGET].state is LinkState.CONFIGURED
    with pytest.raises(InvalidTransition):
        link.to(LinkState.TRUSTED)


def test_a_stranger_that_sent_nothing_valid_is_forgotten_at_once() -> None:
    vehicle = MavlinkVehicle(1, key=KEY)
    forged = bytearray(Station(KEY).frame(heartbeat()))
    forged[-1] ^= 0xFF  # a signature that does not verify
    vehicle.feed(bytes(forged), GCS, 0.0)
    assert GCS not in vehicle.links
    assert vehicle.counters["bad_signature"] == 1


def mission_item(seq: int) -> Any:
    return mavlink.MAVLink_mission_item_int_message(
        1, 1, seq, 3, 16, 0, 1, 0, 0, 0, 0, 10_000_000 + seq, 20_000_000, 0, 0
    )


def count(items: int) -> Any:
    return mavlink.MAVLink_mission_count_message(1, 1, items, 0)


def test_an_upload_receives_awaits_its_verdict_and_is_answered() -> None:
    vehicle = MavlinkVehicle(1, allow_unsigned_control=True)
    station = Station()
    vehicle.feed(station.frame(count(2)), GCS, 0.0)
    upload = vehicle.links[GCS].upload
    assert upload is not None
    assert upload.state is UploadState.RECEIVING
    vehicle.feed(station.frame(mission_item(0)), GCS, 0.1)
    [request] = vehicle.feed(station.frame(mission_item(1)), GCS, 0.2)
    assert upload.state is UploadState.AWAITING_VERDICT
    assert isinstance(request, UploadItems)
    vehicle.answer_upload(request, mavlink.MAV_MISSION_ACCEPTED)
    assert upload.state is UploadState.ANSWERED
    assert vehicle.links[GCS].upload is None


def test_an_upload_is_superseded_by_the_next_or_abandoned_when_an_item_never_comes() -> None:
    vehicle = MavlinkVehicle(1, allow_unsigned_control=True)
    station = Station()
    vehicle.feed(station.frame(count(3)), GCS, 0.0)
    first = vehicle.links[GCS].upload
    vehicle.feed(station.frame(count(2)), GCS, 0.1)
    second = vehicle.links[GCS].upload
    assert first is not None
    assert first.state is UploadState.SUPERSEDED
    assert second is not None
    assert second.state is UploadState.RECEIVING
    now = 0.1
    for _ in range(UPLOAD_RETRIES + 1):
        now += UPLOAD_RETRY_S * 1.01
        vehicle.tick(now)
    assert second.state is UploadState.ABANDONED
    assert vehicle.links[GCS].upload is None
    with pytest.raises(InvalidTransition):
        second.to(UploadState.AWAITING_VERDICT)


def test_a_clear_all_awaits_its_verdict_at_once() -> None:
    vehicle = MavlinkVehicle(1, allow_unsigned_control=True)
    [request] = vehicle.feed(
        Station().frame(mavlink.MAVLink_mission_clear_all_message(1, 1, 0)), GCS, 0.0
    )
    upload = vehicle.links[GCS].upload
    assert upload is not None
    assert upload.state is UploadState.AWAITING_VERDICT
    assert isinstance(request, UploadItems)
    assert request.items == ()


def test_an_admission_slot_is_a_strangers_until_a_session_then_closed_once() -> None:
    policy = AdmissionPolicy(AdmissionLimits(max_connections=8), descriptors=1024)
    slot, evicted = policy.admit("192.0.2.30", 0.0)
    assert slot is not None
    assert evicted is None
    assert slot.state is SlotState.STRANGER
    assert policy.stranger_count == 1
    policy.session_opened(slot)
    assert slot.state is SlotState.SESSION
    assert policy.stranger_count == 0
    policy.release(slot)
    policy.release(slot)  # idempotent
    assert slot.state is SlotState.CLOSED
    # A call that finishes connecting on a connection released meanwhile leaves it closed.
    late, _ = policy.admit("192.0.2.31", 1.0)
    assert late is not None
    policy.release(late)
    policy.session_opened(late)
    assert late.state is SlotState.CLOSED
    with pytest.raises(InvalidTransition):
        late.to(SlotState.SESSION)


def test_a_trusted_listeners_slot_has_a_session_from_the_start() -> None:
    policy = AdmissionPolicy(AdmissionLimits(trusted=True), descriptors=1024)
    slot, _ = policy.admit("127.0.0.1", 0.0)
    assert slot is not None
    assert slot.state is SlotState.SESSION


async def test_the_planner_process_runs_is_lost_runs_again_and_closes() -> None:
    lost: list[str] = []
    planner = PlannerProcess(lambda answer: None, lost.append, backoff_initial=0.01)
    assert planner.state is PlannerState.IDLE
    task = asyncio.get_running_loop().create_task(planner.run())
    try:
        await wait_until(lambda: planner.state is PlannerState.RUNNING, 20)
        first = planner.pid
        assert first is not None
        os.kill(first, signal.SIGKILL)
        await wait_until(lambda: bool(lost), 20)
        await wait_until(lambda: planner.state is PlannerState.RUNNING and planner.pid != first, 20)
    finally:
        task.cancel()
        await asyncio.gather(task, return_exceptions=True)
    assert planner.state is PlannerState.CLOSED
    assert planner.pid is None
    assert planner.restarts == 1
