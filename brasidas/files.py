"""Reading a small file given by the operator (a config, a key) safely: never a hang, never a
flood, a clear error.

A path in a config may name anything: a FIFO (opening it waits for a writer forever), a device
(``/dev/zero`` never ends), a directory, a file of gigabytes. :func:`read_regular_file` takes
regular files of a bounded size only and says what else it found. Blocking: call it at start
or from a thread.
"""

from __future__ import annotations

import os
import stat
from collections.abc import Callable
from pathlib import Path


class FileReadError(Exception):
    """The file is missing, unreadable, not a regular file or too large; the message names the
    file and the reason."""


def read_regular_file(
    path: str | Path,
    what: str,
    max_bytes: int,
    check: Callable[[os.stat_result], None] | None = None,
) -> bytes:
    """The contents of ``path`` (``what`` it is, for the messages: "fleet key", "config"): a
    regular file of at most ``max_bytes``; ``check`` may refuse it by its status first (raise
    :class:`FileReadError`). Raises :class:`FileReadError`."""
    try:
        # O_NONBLOCK: opening a FIFO with no writer returns at once instead of waiting for one.
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise FileReadError(f"{path}: {what} not found") from None
    except OSError as err:
        raise FileReadError(f"{path}: cannot read {what}: {err.strerror}") from None
    try:
        info = os.fstat(fd)
        if not stat.S_ISREG(info.st_mode):
            raise FileReadError(f"{path}: {what} is not a regular file ({_kind(info.st_mode)})")
        if info.st_size > max_bytes:
            raise FileReadError(
                f"{path}: {what} is {info.st_size} bytes, more than the {max_bytes} allowed"
            )
        if check is not None:
            check(info)
        with os.fdopen(fd, "rb", closefd=False) as file:
            data = file.read(max_bytes + 1)
    except OSError as err:
        raise FileReadError(f"{path}: cannot read {what}: {err.strerror}") from None
    finally:
        os.close(fd)
    if len(data) > max_bytes:  # it grew while read
        raise FileReadError(f"{path}: {what} is more than the {max_bytes} bytes allowed")
    return data


def _kind(mode: int) -> str:
    for test, name in (
        (stat.S_ISFIFO, "a FIFO"),
        (stat.S_ISCHR, "a character device"),
        (stat.S_ISBLK, "a block device"),
        (stat.S_ISDIR, "a directory"),
        (stat.S_ISSOCK, "a socket"),
    ):
        if test(mode):
            return name
    return f"mode {mode:o}"
