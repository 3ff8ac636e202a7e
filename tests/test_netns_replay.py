"""Issue 26, defect 1 on a mesh of namespaces: a listener records a signed ground station
driving the platform over the air (MANUAL, the joystick, HOLD); an attacker without the key
sends the recording again from its own address, and from the ground station's own address
with a new source port. Nothing is accepted, nothing drives.

Hosts (tests/netns.py): the rover, the ground station behind a link emulator (its tap is the
listener, tests/hostile.py's :class:`Capture`), and the attacker (:class:`Attacker`)."""

from __future__ import annotations

import asyncio
import hashlib
import socket
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from hostile import Attacker, Capture
from netns import Fleet, network_fixture, requires_netns
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas.netem.netns import Host, TestNetwork, socket_in
from brasidas.netem.relay import UP
from platformd.mavlink.signing import timestamp_at

pytestmark = requires_netns
network = network_fixture("rpl")

PASSPHRASE = "mesh signing passphrase"
MAVLINK_PORT = 14551
GCS_PORT = 14550


class Station:
    """A signed ground station's socket in its namespace (blocking calls with timeouts)."""

    def __init__(self, host: Host, port: int, *, sign: bool) -> None:
        self.sock = socket_in(host.namespace, socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind((host.address, port))
        self.sock.settimeout(0.2)
        self.mav = mavlink.MAVLink(None, 255, 190)
        if sign:
            self.mav.signing.secret_key = hashlib.sha256(PASSPHRASE.encode()).digest()
            self.mav.signing.sign_outgoing = True
            self.mav.signing.link_id = 1
            self.mav.signing.timestamp = timestamp_at(time.time())
        self.parser = mavlink.MAVLink(None, 0, 0)
        self.parser.robust_parsing = True

    def send(self, message: Any, to: tuple[str, int]) -> None:
        self.sock.sendto(message.pack(self.mav), to)
        self.mav.seq = (self.mav.seq + 1) % 256

    def messages(self, seconds: float) -> list[Any]:
        """What arrived within ``seconds``."""
        found: list[Any] = []
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                continue
            found.extend(
                m for m in self.parser.parse_buffer(data) or [] if m.get_type() != "BAD_DATA"
            )
        return found

    def acks(self, seconds: float, command: int) -> list[int]:
        return [
            m.result
            for m in self.messages(seconds)
            if m.get_type() == "COMMAND_ACK" and m.command == command
        ]

    def close(self) -> None:
        self.sock.close()


@pytest.fixture(scope="module")
def mesh(network: TestNetwork, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    directory = Path(tmp_path_factory.mktemp("rpl"))
    key_file = directory / "mavlink.pass"
    key_file.write_text(PASSPHRASE + "\n")
    key_file.chmod(0o600)
    fleet = Fleet(network, directory)
    rover = network.add_host("rover")
    gcs_host = network.add_host("gcs", impaired=True)
    attacker = Attacker(network.add_host("mallory"))
    capture = Capture()
    assert gcs_host.relay is not None
    gcs_host.relay.taps.append(capture.tap)
    fleet.platform(
        rover,
        "rover-r",
        "mavlink.enabled=true",
        f"mavlink.host={rover.address}",
        f"mavlink.port={MAVLINK_PORT}",
        f'mavlink.targets=["{gcs_host.address}:{GCS_PORT}"]',
        f"mavlink.signing_key_file={key_file}",
        "navcam.enabled=false",
        "audio.enabled=false",
    )
    try:
        yield rover, gcs_host, attacker, capture
    finally:
        attacker.close()
        fleet.stop()
        gcs_host.relay.taps.remove(capture.tap)


async def test_a_recorded_signed_session_replayed_over_the_mesh_is_refused(mesh: Any) -> None:
    rover, gcs_host, attacker, capture = mesh
    vehicle = (rover.address, MAVLINK_PORT)
    gcs = Station(gcs_host, GCS_PORT, sign=True)
    try:
        # The rover is up once its heartbeats reach the configured ground station.
        deadline = time.monotonic() + 60
        while not any(
            m.get_type() == "HEARTBEAT" for m in await asyncio.to_thread(gcs.messages, 0.5)
        ):
            assert time.monotonic() < deadline, "no heartbeat from the rover"
        manual = mavlink.MAVLink_command_long_message(
            1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 0, 0, 0, 0, 0, 0
        )
        hold = mavlink.MAVLink_command_long_message(
            1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0
        )
        gcs.send(manual, vehicle)
        assert await asyncio.to_thread(gcs.acks, 2.0, mavlink.MAV_CMD_DO_SET_MODE) == [0]
        for _ in range(10):
            gcs.send(mavlink.MAVLink_manual_control_message(1, 500, 0, 500, 0, 0), vehicle)
            await asyncio.sleep(0.05)
        gcs.send(hold, vehicle)
        assert await asyncio.to_thread(gcs.acks, 2.0, mavlink.MAV_CMD_DO_SET_MODE) == [0]
    finally:
        gcs.close()
    recorded = [d for _, d in capture.select(UP, "udp", MAVLINK_PORT)]
    assert len(recorded) >= 12  # the listener heard the whole session

    # From the attacker's own address (where it listens for the answers), a second later.
    listener = Station(attacker.host, 40001, sign=False)
    try:
        await asyncio.sleep(1.0)
        attacker.replay(recorded, (attacker.host.address, 40001))
        assert await asyncio.to_thread(listener.messages, 2.0) == []  # not one answer
    finally:
        listener.close()
    # From the ground station's own address, a new source port: no ACK reaches it there.
    gcs = Station(gcs_host, 40002, sign=False)
    try:
        attacker.replay(recorded, (gcs_host.address, 40002))
        acks = await asyncio.to_thread(gcs.acks, 2.0, mavlink.MAV_CMD_DO_SET_MODE)
        assert acks == []
    finally:
        gcs.close()
