"""The platform's boot number (issue 26, defect 6): kept on disk, it only grows.

Beacons carry it beside their sequence number, so a station refuses a beacon of an earlier
boot (:class:`brasidas.codecs.beacon.ReplayGuard`). Each start takes the larger of the saved
number + 1 and the wall clock's seconds (a platform whose state folder was lost still starts
above what stations have seen, if its clock is set), and saves it before the first beacon.
"""

from __future__ import annotations

import logging
from pathlib import Path

from brasidas.autonomy.route import write_atomically
from brasidas.files import FileReadError, read_regular_file
from brasidas.security import state_dir

_LOGGER = logging.getLogger(__name__)

BOOT_MAX = 0xFFFF_FFFF
"""The beacon's field is 32 bits."""


def boot_counter_path() -> Path:
    return state_dir() / "boot-counter"


def next_boot(path: Path, wall: float) -> int:
    """This start's boot number, saved to ``path``. Blocking: call it in a thread.
    Raises OSError when it cannot be saved (the platform must not reuse a number)."""
    saved = 0
    try:
        text = read_regular_file(path, "boot counter", 64).decode("ascii", "replace").strip()
        saved = int(text) if text.isdecimal() else 0
        if not text.isdecimal():
            _LOGGER.error("%s: not a boot number (%r); starting from the clock", path, text)
    except FileReadError as err:
        if path.exists() or path.is_symlink():
            _LOGGER.error("%s; starting from the clock", err)
    boot = min(BOOT_MAX, max(saved + 1, int(wall)))
    write_atomically(path, str(boot))
    return boot
