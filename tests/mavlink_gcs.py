"""A ground station for tests: pymavlink's encoder and parser over an asyncio UDP socket.

It listens on an ephemeral loopback port (the platform's ``mavlink.targets`` names it) and
answers to whichever address the vehicle sends from, as QGroundControl does.
"""

from __future__ import annotations

import asyncio
import hashlib
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas.config import PlatformConfig
from platformd.mavlink.signing import timestamp_at
from platformd.sim.demo_area import offset

LAT, LON = 37.9415, 23.6530
"""Where the simulated rover starts: the demo field's south-west corner of the loop."""


def sim_rover_config(tmp_path: Path, target_port: int, *overrides: str) -> PlatformConfig:
    """A --sim rover (motors, GPS, the demo map) whose MAVLink endpoint sends to
    ``127.0.0.1:target_port``; its map and route files in ``tmp_path``."""
    from conftest import quiet_platform_config

    return quiet_platform_config(
        "sim.enabled=true",
        "motor.enabled=true",
        "gps.enabled=true",
        f"sim.latitude={LAT}",
        f"sim.longitude={LON}",
        f"map.file={tmp_path / 'map.geojson'}",
        f"autonomy.route_file={tmp_path / 'route.json'}",
        "mavlink.enabled=true",
        f'mavlink.targets=["127.0.0.1:{target_port}"]',
        *overrides,
    )


FAST_ROVER = (
    "platform.max_speed_kmh=18",
    "autonomy.cruise_speed_kmh=18",
    "autonomy.lookahead_m=3",
    "autonomy.decel_mps2=6",
    "autonomy.max_turn_rate_dps=86",
)
"""A rover three times the default speed, for tests about where a mission goes rather than how
fast (the planner, the pursuit and the arrival are the same code at any speed)."""


def at(east: float, north: float) -> tuple[float, float]:
    """Metres east and north of the start, as (lat, lon)."""
    return offset(LAT, LON, east, north)


class Gcs(asyncio.DatagramProtocol):
    def __init__(self, system: int = 255, component: int = 190) -> None:
        self.mav = mavlink.MAVLink(None, system, component)
        self.parser = mavlink.MAVLink(None, 0, 0)
        self.parser.robust_parsing = True
        self.transport: asyncio.DatagramTransport | None = None
        self.vehicle: tuple[str, int] | None = None
        self.received: list[Any] = []
        self.frames: list[bytes] = []
        """Every datagram sent, as sent (for replay tests)."""
        self.bytes_received = 0
        self._changed = asyncio.Event()

    @classmethod
    async def open(cls, system: int = 255, component: int = 190) -> Gcs:
        loop = asyncio.get_running_loop()
        _, gcs = await loop.create_datagram_endpoint(
            lambda: cls(system, component), local_addr=("127.0.0.1", 0)
        )
        return gcs

    @property
    def port(self) -> int:
        assert self.transport is not None
        return int(self.transport.get_extra_info("sockname")[1])

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = transport  # type: ignore[assignment]

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        self.vehicle = (addr[0], addr[1])
        self.bytes_received += len(data)
        for message in self.parser.parse_buffer(data) or []:
            if message.get_type() != "BAD_DATA":
                self.received.append(message)
        self._changed.set()

    def sign(self, passphrase: str, link_id: int = 1) -> None:
        self.mav.signing.secret_key = hashlib.sha256(passphrase.encode()).digest()
        self.mav.signing.sign_outgoing = True
        self.mav.signing.link_id = link_id
        self.mav.signing.timestamp = timestamp_at(time.time())

    def send(self, message: Any) -> bytes:
        assert self.transport is not None and self.vehicle is not None
        frame = message.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        self.frames.append(frame)
        self.transport.sendto(frame, self.vehicle)
        return frame

    def send_raw(self, frame: bytes) -> None:
        assert self.transport is not None and self.vehicle is not None
        self.transport.sendto(frame, self.vehicle)

    async def expect(
        self,
        kind: str,
        where: Callable[[Any], bool] = lambda message: True,
        timeout: float = 10.0,
        *,
        since: int | None = None,
    ) -> Any:
        """The first message of ``kind`` matching ``where`` (received from ``since`` on)."""
        start = len(self.received) if since is None else since

        async def wait() -> Any:
            index = start
            while True:
                while index < len(self.received):
                    message = self.received[index]
                    index += 1
                    if message.get_type() == kind and where(message):
                        return message
                self._changed.clear()
                await self._changed.wait()

        return await asyncio.wait_for(wait(), timeout)

    def mark(self) -> int:
        """Where ``expect(since=...)`` starts: messages from now on."""
        return len(self.received)

    def texts(self, since: int = 0) -> list[str]:
        """STATUSTEXTs from ``since`` on, chunks joined (MAVLink 2's id and chunk_seq)."""
        texts: list[str] = []
        open_ids: dict[int, int] = {}
        for message in self.received[since:]:
            if message.get_type() != "STATUSTEXT":
                continue
            if message.id and message.id in open_ids:
                texts[open_ids[message.id]] += message.text
                continue
            if message.id:
                open_ids[message.id] = len(texts)
            texts.append(message.text)
        return texts

    async def expect_text(
        self, where: Callable[[str], bool], since: int, timeout: float = 10.0
    ) -> str:
        """The first whole STATUSTEXT matching ``where``."""

        async def wait() -> str:
            while True:
                for text in self.texts(since):
                    if where(text):
                        return text
                self._changed.clear()
                await self._changed.wait()

        return await asyncio.wait_for(wait(), timeout)

    def close(self) -> None:
        if self.transport is not None:
            self.transport.close()
            self.transport = None

    async def command(self, command: int, *params: float, component: int = 1) -> Any:
        """COMMAND_LONG to the vehicle; its COMMAND_ACK."""
        since = self.mark()
        values = [*params, *[0.0] * (7 - len(params))]
        self.send(mavlink.MAVLink_command_long_message(1, component, command, 0, *values))
        return await self.expect("COMMAND_ACK", lambda m: m.command == command, since=since)

    async def upload(self, items: list[Any], mission_type: int = 0) -> Any:
        """The mission upload protocol as a ground station runs it; the MISSION_ACK."""
        since = self.mark()
        self.send(mavlink.MAVLink_mission_count_message(1, 1, len(items), mission_type))
        sent = 0
        index = since
        while True:
            message = await self._next_upload_message(index)
            index = self.received.index(message, index) + 1
            if message.get_type() == "MISSION_ACK":
                return message
            item = items[message.seq]
            self.send(item)
            sent += 1

    async def _next_upload_message(self, since: int) -> Any:
        async def wait() -> Any:
            index = since
            while True:
                while index < len(self.received):
                    message = self.received[index]
                    index += 1
                    if message.get_type() in ("MISSION_REQUEST_INT", "MISSION_ACK"):
                        return message
                self._changed.clear()
                await self._changed.wait()

        return await asyncio.wait_for(wait(), 10.0)

    async def download(self, mission_type: int = 0) -> list[Any]:
        since = self.mark()
        self.send(mavlink.MAVLink_mission_request_list_message(1, 1, mission_type))
        count = await self.expect("MISSION_COUNT", since=since)
        items = []
        for seq in range(count.count):
            mark = self.mark()
            self.send(mavlink.MAVLink_mission_request_int_message(1, 1, seq, mission_type))
            items.append(
                await self.expect("MISSION_ITEM_INT", lambda m, s=seq: m.seq == s, since=mark)
            )
        self.send(mavlink.MAVLink_mission_ack_message(1, 1, 0, mission_type))
        return items


def waypoint(seq: int, lat: float, lon: float, mission_type: int = 0) -> Any:
    return mavlink.MAVLink_mission_item_int_message(
        1,
        1,
        seq,
        mavlink.MAV_FRAME_GLOBAL_RELATIVE_ALT,
        mavlink.MAV_CMD_NAV_WAYPOINT,
        0,
        1,
        0,
        0,
        0,
        0,
        round(lat * 1e7),
        round(lon * 1e7),
        0,
        mission_type,
    )


def fence_item(seq: int, command: int, param1: float, lat: float, lon: float) -> Any:
    return mavlink.MAVLink_mission_item_int_message(
        1,
        1,
        seq,
        mavlink.MAV_FRAME_GLOBAL,
        command,
        0,
        1,
        param1,
        0,
        0,
        0,
        round(lat * 1e7),
        round(lon * 1e7),
        0,
        1,
    )


QGC_COMMAND_TIMEOUT = 1.2
"""QGroundControl's wait for a COMMAND_ACK before each of its three retries."""
QGC_FTP_TIMEOUT = 1.0
QGC_PARAMS_FIRST_TIMEOUT = 5.0
QGC_TRANSFER_TIMEOUT = 1.5
PARAM_FILE = b"@PARAM/param.pck?withdefaults=1"


async def qgc_connect(gcs: Gcs) -> dict[str, Any]:
    """QGroundControl 4.x's connect (``InitialConnectStateMachine``) replayed with its
    timeouts: autopilot version, protocol version, parameters (MAVFTP first, then the
    parameter protocol), mission, fence and rally downloads. Each step must be answered inside
    QGC's timeout (a timeout is a stall a user sees: raises ``TimeoutError``). Returns what
    each step got."""
    got: dict[str, Any] = {}
    for name, message_id in (
        ("AUTOPILOT_VERSION", mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION),
        ("PROTOCOL_VERSION", 300),  # not in pymavlink 2.4 dialects
    ):
        since = gcs.mark()
        gcs.send(
            mavlink.MAVLink_command_long_message(
                1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, message_id, 0, 0, 0, 0, 0, 0
            )
        )
        got[f"{name}_ack"] = await gcs.expect(
            "COMMAND_ACK",
            lambda m: m.command == mavlink.MAV_CMD_REQUEST_MESSAGE,
            QGC_COMMAND_TIMEOUT,
            since=since,
        )
        if got[f"{name}_ack"].result == mavlink.MAV_RESULT_ACCEPTED:
            got[name] = await gcs.expect(name, timeout=QGC_COMMAND_TIMEOUT, since=since)
    # Parameters: MAVFTP's OpenFileRO of the parameter file; at once to PARAM_REQUEST_LIST
    # only on "file not found" (QGC's other NAKs wait out its retries).
    request = bytearray(251)
    request[0:2] = (1).to_bytes(2, "little")
    request[3], request[4] = 4, len(PARAM_FILE)
    request[12 : 12 + len(PARAM_FILE)] = PARAM_FILE
    since = gcs.mark()
    gcs.send(mavlink.MAVLink_file_transfer_protocol_message(0, 1, 1, list(request)))
    got["ftp"] = bytes(
        (await gcs.expect("FILE_TRANSFER_PROTOCOL", timeout=QGC_FTP_TIMEOUT, since=since)).payload
    )
    if got["ftp"][3] != 129 or got["ftp"][12] != 10:
        raise TimeoutError("MAVFTP: not a FileNotFound NAK: QGroundControl waits out its retries")
    since = gcs.mark()
    gcs.send(mavlink.MAVLink_param_request_list_message(1, 1))
    first = await gcs.expect("PARAM_VALUE", timeout=QGC_PARAMS_FIRST_TIMEOUT, since=since)

    def indexes() -> set[int]:
        return {m.param_index for m in gcs.received[since:] if m.get_type() == "PARAM_VALUE"}

    while len(indexes()) < first.param_count:
        await gcs.expect("PARAM_VALUE", timeout=QGC_TRANSFER_TIMEOUT)
    got["params_complete"] = time.monotonic()
    # Fence and rally only over a link known to be MAVLink 2 (else QGC turns fences off).
    protocol = got.get("PROTOCOL_VERSION")
    kinds = (0, 1, 2) if protocol is not None and protocol.max_version >= 200 else (0,)
    got["transfers"] = kinds
    for mission_type in kinds:
        since = gcs.mark()
        gcs.send(mavlink.MAVLink_mission_request_list_message(1, 1, mission_type))
        count = await gcs.expect(
            "MISSION_COUNT",
            lambda m, t=mission_type: m.mission_type == t,
            QGC_TRANSFER_TIMEOUT,
            since=since,
        )
        for seq in range(count.count):
            mark = gcs.mark()
            gcs.send(mavlink.MAVLink_mission_request_int_message(1, 1, seq, mission_type))
            await gcs.expect(
                "MISSION_ITEM_INT", lambda m, s=seq: m.seq == s, QGC_TRANSFER_TIMEOUT, since=mark
            )
        if count.count:
            gcs.send(mavlink.MAVLink_mission_ack_message(1, 1, 0, mission_type))
    return got
