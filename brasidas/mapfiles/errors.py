"""The one refusal every reader raises, and the size of file a reader accepts."""

from __future__ import annotations

MAX_FILE_BYTES = 4 * 1024 * 1024
"""A bigger file is refused before it is read (a map has 20 000 vertices at most)."""


class FileRefused(ValueError):
    """A map or route file refused; the message names the feature, row or line and why."""
