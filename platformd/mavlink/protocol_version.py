"""PROTOCOL_VERSION (message 300), which pymavlink's generated dialects lack.

QGroundControl asks for it with MAV_CMD_REQUEST_MESSAGE at connect; refused or unanswered, it
assumes MAVLink 1 and turns fences off. The class follows pymavlink's generated ones (common.xml's
fields and CRC extra) and is registered in the dialect's message map, so pymavlink parsers
(ours, the tests', MAVProxy's) decode it too.
"""

from __future__ import annotations

import struct
from collections.abc import Sequence
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

MSG_ID = 300
CRC_EXTRA = 217
"""common.xml's PROTOCOL_VERSION fields' CRC (what pymavlink's generator computes from them)."""
MAVLINK_VERSION = 200
"""MAVLink 2 (version times 100)."""


class ProtocolVersionMessage(mavlink.MAVLink_message):  # type: ignore[misc]
    """Version and version range of this MAVLink implementation."""

    id = MSG_ID
    msgname = "PROTOCOL_VERSION"
    fieldnames = [
        "version",
        "min_version",
        "max_version",
        "spec_version_hash",
        "library_version_hash",
    ]
    ordered_fieldnames = fieldnames
    fieldtypes = ["uint16_t", "uint16_t", "uint16_t", "uint8_t", "uint8_t"]
    fielddisplays_by_name: dict[str, str] = {}
    fieldenums_by_name: dict[str, str] = {}
    fieldunits_by_name: dict[str, str] = {}
    native_format = bytearray(b"<HHHBB")
    orders = [0, 1, 2, 3, 4]
    lengths = [1, 1, 1, 8, 8]
    array_lengths = [0, 0, 0, 8, 8]
    crc_extra = CRC_EXTRA
    unpacker = struct.Struct("<HHH8B8B")
    instance_field = None
    instance_offset = -1

    def __init__(
        self,
        version: int,
        min_version: int,
        max_version: int,
        spec_version_hash: Sequence[int],
        library_version_hash: Sequence[int],
    ) -> None:
        super().__init__(MSG_ID, self.msgname)
        self._fieldnames = self.fieldnames
        self._instance_field = None
        self._instance_offset = -1
        self.version = version
        self.min_version = min_version
        self.max_version = max_version
        self.spec_version_hash = spec_version_hash
        self.library_version_hash = library_version_hash

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        packed: bytes = self._pack(
            mav,
            self.crc_extra,
            self.unpacker.pack(
                self.version,
                self.min_version,
                self.max_version,
                *self.spec_version_hash,
                *self.library_version_hash,
            ),
            force_mavlink1=force_mavlink1,
        )
        return packed


mavlink.mavlink_map.setdefault(MSG_ID, ProtocolVersionMessage)


def protocol_version() -> ProtocolVersionMessage:
    """MAVLink 2 only (the endpoint signs and speaks MAVLink 2); no hashes known."""
    return ProtocolVersionMessage(
        MAVLINK_VERSION, MAVLINK_VERSION, MAVLINK_VERSION, [0] * 8, [0] * 8
    )
