"""Fleet key and the HMACs built on it (R-0.9).

The fleet key is 32 random bytes stored as hex in a file only its owner can read. Nothing
derived from it travels in the clear except truncated HMAC tags.
"""

from __future__ import annotations

import hashlib
import hmac
import os
import secrets
from pathlib import Path


class FleetKeyError(Exception):
    """The fleet key is missing or unreadable."""


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
    """Read the fleet key at ``path``; raises :class:`FleetKeyError` with a clear message."""
    try:
        text = path.read_text().strip()
    except FileNotFoundError:
        raise FleetKeyError(
            f"{path}: fleet key not found (create one with 'brasidas-station keygen')"
        ) from None
    except OSError as err:
        raise FleetKeyError(f"{path}: cannot read fleet key: {err.strerror}") from None
    try:
        key = bytes.fromhex(text)
    except ValueError:
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
