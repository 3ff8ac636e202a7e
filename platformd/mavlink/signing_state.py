"""The signing clock and replay table kept across restarts, and GPS time for the clock.

Loaded before the endpoint binds, saved every :data:`~platformd.mavlink.signing.SAVE_INTERVAL_S`
while it changes (marked unclean: a crash after it loses at most that much, covered by
:data:`~platformd.mavlink.signing.UNCLEAN_STOP_SLACK`) and once more, clean, when it stops.
"""

from __future__ import annotations

import asyncio
import logging
from datetime import datetime
from pathlib import Path

from brasidas.security import state_dir
from platformd.mavlink.signing import (
    SAVE_INTERVAL_S,
    SignatureCheck,
    load_state,
    save_state,
    timestamp_at,
)

_LOGGER = logging.getLogger(__name__)

STATE_FILE_NAME = "mavlink-signing.json"


def signing_state_path(configured: str) -> Path:
    """``mavlink.signing_state_file``, or ``$XDG_STATE_HOME/brasidas/mavlink-signing.json``."""
    return Path(configured).expanduser() if configured else state_dir() / STATE_FILE_NAME


def gps_timestamp(utc: str) -> int:
    """The signing timestamp of a GPS fix's UTC time; 0 while the receiver knows no date."""
    if "T" not in utc:
        return 0
    try:
        return timestamp_at(datetime.fromisoformat(utc.replace("Z", "+00:00")).timestamp())
    except ValueError:
        return 0


class SigningStateFile:
    """Keeps one :class:`SignatureCheck`'s state in a file (nothing without signing)."""

    def __init__(self, check: SignatureCheck | None, path: Path) -> None:
        self.check = check
        self.path = path

    async def restore(self) -> None:
        """Take the saved state, then mark the file unclean until the next clean stop."""
        if self.check is None:
            return
        try:
            saved = await asyncio.to_thread(load_state, self.path)
        except ValueError as err:
            # Still start (a damaged disk must not ground the robot): the clock's minute
            # window refuses every older capture; only the last minute's is not covered.
            _LOGGER.error("MAVLink: %s; replay state starts empty", err)
            saved = None
        if saved is not None:
            self.check.restore(saved)
        await self._save(clean=False)

    async def save_forever(self) -> None:
        while True:
            await asyncio.sleep(SAVE_INTERVAL_S)
            if self.check is not None and self.check.changed:
                await self._save(clean=False)

    async def save_at_stop(self) -> None:
        await self._save(clean=True)

    async def _save(self, *, clean: bool) -> None:
        if self.check is None:
            return
        try:
            await asyncio.to_thread(save_state, self.path, self.check.state(), clean=clean)
        except OSError as err:
            _LOGGER.error("MAVLink: cannot save the signing state to %s: %s", self.path, err)
