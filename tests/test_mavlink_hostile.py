"""Issue 26 on the sans-IO MAVLink vehicle: a spoofed unsigned video request starts no video
(defect 2), strangers cannot fill the address table against a signed ground station (defect 8),
and unsigned control off loopback is refused at start (defect 9)."""

from __future__ import annotations

import hashlib
from typing import Any

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas.config import ConfigError, PlatformConfig, load_config
from platformd.mavlink.signing import timestamp_at
from platformd.mavlink.vehicle import (
    MAX_LINKS,
    CameraInfo,
    MavlinkVehicle,
    SetMode,
    StartVideo,
)

KEY = hashlib.sha256(b"fleet passphrase").digest()
TARGET = ("192.0.2.1", 14550)
VICTIM = ("192.0.2.77", 5600)
CAMERA = CameraInfo(640, 480, 30.0, 1500, 5600)
WALL = 1_790_000_000.0


def frame(message: Any, *, signed: bool = False, system: int = 249) -> bytes:
    mav = mavlink.MAVLink(None, system, 190)
    if signed:
        mav.signing.secret_key = KEY
        mav.signing.sign_outgoing = True
        mav.signing.link_id = 2
        mav.signing.timestamp = timestamp_at(WALL)
    return bytes(message.pack(mav))


VIDEO_REQUEST = mavlink.MAVLink_command_long_message(
    1,
    100,
    mavlink.MAV_CMD_REQUEST_MESSAGE,
    0,
    mavlink.MAVLINK_MSG_ID_VIDEO_STREAM_INFORMATION,
    0,
    0,
    0,
    0,
    0,
    0,
)


def vehicle() -> MavlinkVehicle:
    return MavlinkVehicle(1, key=KEY, targets=(TARGET,), camera=CAMERA, wall_clock=lambda: WALL)


def test_a_spoofed_unsigned_video_request_starts_no_video() -> None:
    rover = vehicle()
    request = frame(VIDEO_REQUEST)
    received = 0
    for n in range(5):  # one every 4 s, as the attack sustained it
        assert not [r for r in rover.feed(request, VICTIM, n * 4.0) if isinstance(r, StartVideo)]
        received += len(request)
    sent = sum(len(data) for data, peer in rover.take() if peer == VICTIM)
    assert sent <= received  # the answers too: no more than the attacker spent
    assert rover.counters["video_refused"] == 5
    # Signed, or from a configured target: the video starts.
    [signed] = rover.feed(frame(VIDEO_REQUEST, signed=True), ("192.0.2.20", 14550), 30.0)
    assert isinstance(signed, StartVideo)
    assert signed.signed
    [target] = rover.feed(request, TARGET, 31.0)
    assert isinstance(target, StartVideo)


def test_strangers_cannot_fill_the_table_against_a_signed_ground_station() -> None:
    rover = vehicle()
    heartbeat = mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3
    )
    for port in range(40000, 40000 + 2 * MAX_LINKS):  # one heartbeat each, every 2 s
        rover.feed(frame(heartbeat), ("192.0.2.66", port), 1.0)
    assert rover.counters["links_refused"] > 0
    assert len(rover.links) < MAX_LINKS
    hold = mavlink.MAVLink_command_long_message(
        1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0
    )
    gcs = ("192.0.2.30", 14550)
    [request] = rover.feed(frame(hold, signed=True, system=255), gcs, 1.5)
    assert isinstance(request, SetMode)
    assert request.signed
    assert gcs in rover.links


@pytest.mark.parametrize(
    ("overrides", "refused"),
    [
        (["mavlink.host=0.0.0.0"], True),
        (["mavlink.host=10.1.2.3"], True),
        (["mavlink.host=127.0.0.1"], False),
        (["mavlink.host=::1"], False),
        (
            [
                "mavlink.host=0.0.0.0",
                "mavlink.unsigned_control_off_loopback_i_accept_the_risk=true",
            ],
            False,
        ),
    ],
)
def test_unsigned_control_off_loopback_needs_the_explicit_risk_key(
    overrides: list[str], refused: bool
) -> None:
    settings = ["mavlink.allow_unsigned_control=true", *overrides]
    if refused:
        with pytest.raises(ConfigError, match="allow_unsigned_control.*loopback"):
            load_config(PlatformConfig, None, settings)
    else:
        assert load_config(PlatformConfig, None, settings).mavlink.allow_unsigned_control
