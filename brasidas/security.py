"""Fleet key and the HMACs built on it (R-0.9).

The fleet key is 32 random bytes stored as hex in a file only its owner can read (a key file
others can read is refused, as ssh refuses one: :func:`read_private_file`, for every key file).
Nothing derived from it travels in the clear except truncated HMAC tags.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
import stat
from pathlib import Path

from brasidas.files import FileReadError, read_regular_file

MAX_KEY_FILE_BYTES = 4096
"""A key file is a few dozen bytes of hex; anything past this is not one."""


class PrivateFileError(FileReadError):
    """A private file (a key) is missing, unreadable, not a regular file, too large or
    accessible by others; the message names the file, the reason and the fix."""


class FleetKeyError(PrivateFileError):
    """The fleet key is missing or unreadable."""


def read_private_file(path: Path, what: str, max_bytes: int = MAX_KEY_FILE_BYTES) -> bytes:
    """The contents of ``path``, a secret (``what``: "fleet key", "MAVLink signing key"), under
    the rules ssh applies to a private key: a regular file (a FIFO or a device never hangs or
    floods the start) of at most ``max_bytes``, owned by this user (or root), and neither
    readable nor writable by group or others — else :class:`PrivateFileError` naming the
    ``chmod`` that fixes it. Blocking: call it at start or from a thread."""

    def private(info: os.stat_result) -> None:
        if info.st_uid not in (os.geteuid(), 0):
            raise PrivateFileError(
                f"{path}: the {what} belongs to uid {info.st_uid}, not to this user "
                f"(uid {os.geteuid()}): chown it"
            )
        mode = stat.S_IMODE(info.st_mode)
        if mode & 0o077:
            raise PrivateFileError(
                f"{path}: permissions {mode:04o} for the {what} are too open: it must be "
                f"accessible by its owner only (chmod 600 {path})"
            )

    try:
        return read_regular_file(path, what, max_bytes, private)
    except PrivateFileError:
        raise
    except FileReadError as err:
        raise PrivateFileError(str(err)) from None


def state_dir() -> Path:
    """``$XDG_STATE_HOME/brasidas`` (default ``~/.local/state/brasidas``)."""
    base = os.environ.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "brasidas"


def default_key_path() -> Path:
    return state_dir() / "fleet.key"


def key_path(configured: str) -> Path:
    return Path(configured).expanduser() if configured else default_key_path()


def generate_key(path: Path, *, overwrite: bool = False) -> bytes:
    """Write a new fleet key to ``path`` (mode 0600) and return it."""
    path.parent.mkdir(parents=True, exist_ok=True)
    key = secrets.token_bytes(32)
    flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if overwrite else os.O_EXCL)
    fd = os.open(path, flags, 0o600)
    with os.fdopen(fd, "w") as file:
        file.write(key.hex() + "\n")
    return key


def load_key(path: Path) -> bytes:
    """Read the fleet key at ``path`` (:func:`read_private_file`'s rules); raises
    :class:`FleetKeyError` with a clear message."""
    if not path.exists() and not path.is_symlink():
        raise FleetKeyError(
            f"{path}: fleet key not found (create one with 'brasidas-station keygen')"
        )
    try:
        data = read_private_file(path, "fleet key")
    except PrivateFileError as err:
        raise FleetKeyError(str(err)) from None
    try:
        key = bytes.fromhex(data.decode("ascii").strip())
    except ValueError:  # UnicodeDecodeError included
        raise FleetKeyError(f"{path}: fleet key is not hex") from None
    if len(key) < 16:
        raise FleetKeyError(f"{path}: fleet key too short ({len(key)} bytes, need 16 or more)")
    return key


def load_or_create_key(path: Path) -> bytes:
    """The key at ``path``, creating it first when absent (simulation and the demo only)."""
    try:
        return load_key(path)
    except FleetKeyError:
        if path.exists():
            raise
    try:
        return generate_key(path)
    except FileExistsError:  # another daemon created it just now
        return load_key(path)


def tag(key: bytes, *parts: bytes | str, length: int = 32) -> bytes:
    """HMAC-SHA256 over the parts (each length-prefixed), truncated to ``length`` bytes."""
    mac = hmac.new(key, digestmod=hashlib.sha256)
    for part in parts:
        data = part.encode() if isinstance(part, str) else part
        mac.update(len(data).to_bytes(4, "big"))
        mac.update(data)
    return mac.digest()[:length]


def verify(expected: bytes, received: bytes) -> bool:
    return hmac.compare_digest(expected, received)


def session_key(fleet_key: bytes, token: str, platform_nonce: str, station_nonce: str) -> bytes:
    """The per-session key both ends derive after connect; never sent."""
    return tag(fleet_key, b"brasidas-session", token, platform_nonce, station_nonce)


def connect_proof(
    key: bytes, platform_id: str, station_id: str, nonce: str, station_nonce: str
) -> str:
    """What the station sends to prove it holds the fleet key."""
    return tag(key, b"brasidas-connect", platform_id, station_id, nonce, station_nonce).hex()


def accept_proof(
    key: bytes, platform_id: str, station_id: str, nonce: str, station_nonce: str, token: str
) -> str:
    """What the platform answers to prove it holds the fleet key too."""
    return tag(key, b"brasidas-accept", platform_id, station_id, nonce, station_nonce, token).hex()
