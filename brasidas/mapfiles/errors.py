"""The one refusal every reader raises, and the size of file a reader accepts."""

from __future__ import annotations

from brasidas.limits import FILE_MAX_BYTES

MAX_FILE_BYTES = FILE_MAX_BYTES
"""A bigger file is refused before it is read (a map has 20 000 vertices at most)."""


class FileRefused(ValueError):
    """A map or route file refused; the message names the feature, row or line and why."""
