"""MAVFTP (FILE_TRANSFER_PROTOCOL) answered as a vehicle with no files.

The vehicle serves no files: parameters come over PARAM_REQUEST_LIST. What matters is *how*
it says no. QGroundControl opens ``@PARAM/param.pck`` first and falls back to the parameter
protocol at once only on a NAK with ``FileNotFound``; any other NAK costs its retries and
timeouts (about ten seconds of "Loading parameters" on every connect). MAVProxy falls back on
any NAK. So: opening, listing or checksumming anything is "file not found", closing sessions
is acknowledged, reads need a session that cannot exist, and writes are refused.
"""

from __future__ import annotations

import enum

PAYLOAD_SIZE = 251
"""FILE_TRANSFER_PROTOCOL's payload length."""


class Opcode(enum.IntEnum):
    """MAVFTP's opcodes (mavlink.io "File Transfer Protocol")."""

    NONE = 0
    TERMINATE_SESSION = 1
    RESET_SESSIONS = 2
    LIST_DIRECTORY = 3
    OPEN_FILE_RO = 4
    READ_FILE = 5
    CREATE_FILE = 6
    WRITE_FILE = 7
    REMOVE_FILE = 8
    CREATE_DIRECTORY = 9
    REMOVE_DIRECTORY = 10
    OPEN_FILE_WO = 11
    TRUNCATE_FILE = 12
    RENAME = 13
    CALC_FILE_CRC32 = 14
    BURST_READ_FILE = 15
    ACK = 128
    NAK = 129


class FtpError(enum.IntEnum):
    """The first data byte of a NAK."""

    NONE = 0
    FAIL = 1
    FAIL_ERRNO = 2
    INVALID_DATA_SIZE = 3
    INVALID_SESSION = 4
    NO_SESSIONS_AVAILABLE = 5
    EOF = 6
    UNKNOWN_COMMAND = 7
    FILE_EXISTS = 8
    FILE_PROTECTED = 9
    FILE_NOT_FOUND = 10


_NOT_FOUND = {Opcode.OPEN_FILE_RO, Opcode.LIST_DIRECTORY, Opcode.CALC_FILE_CRC32}
_NO_SESSION = {Opcode.READ_FILE, Opcode.BURST_READ_FILE, Opcode.WRITE_FILE}
_PROTECTED = {
    Opcode.CREATE_FILE,
    Opcode.REMOVE_FILE,
    Opcode.CREATE_DIRECTORY,
    Opcode.REMOVE_DIRECTORY,
    Opcode.OPEN_FILE_WO,
    Opcode.TRUNCATE_FILE,
    Opcode.RENAME,
}


def reply(request: bytes) -> bytes | None:
    """The answer to one request payload; None for a payload too short to answer or a
    reply (ACK/NAK) a confused peer sent back."""
    if len(request) < 12:
        return None
    opcode = request[3]
    if opcode in (Opcode.ACK, Opcode.NAK):
        return None
    answer = bytearray(PAYLOAD_SIZE)
    seq = int.from_bytes(request[0:2], "little")
    answer[0:2] = ((seq + 1) & 0xFFFF).to_bytes(2, "little")
    answer[2] = request[2]
    answer[5] = opcode
    if opcode in (Opcode.TERMINATE_SESSION, Opcode.RESET_SESSIONS):
        answer[3] = Opcode.ACK
        return bytes(answer)
    if opcode in _NOT_FOUND:
        error = FtpError.FILE_NOT_FOUND
    elif opcode in _NO_SESSION:
        error = FtpError.INVALID_SESSION
    elif opcode in _PROTECTED:
        error = FtpError.FILE_PROTECTED
    else:
        error = FtpError.UNKNOWN_COMMAND
    answer[3], answer[4], answer[12] = Opcode.NAK, 1, error
    return bytes(answer)
