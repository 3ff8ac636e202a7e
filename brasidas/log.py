"""Logging to stderr: journald-friendly priority prefixes under systemd, timestamps on a terminal.

Every message is one line: control characters in it, which a peer may put in any text it sends
(a station id, a host name), are escaped, so a log line cannot be forged."""

from __future__ import annotations

import argparse
import logging
import os
import sys
import unicodedata

LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")

_PRIORITY = {
    logging.CRITICAL: 2,
    logging.ERROR: 3,
    logging.WARNING: 4,
    logging.INFO: 6,
    logging.DEBUG: 7,
}


def escape_control(text: str) -> str:
    """``text`` with every control, format and line/paragraph separator character written as
    its Python escape (``\\n``, ``\\x1b``, ``\\u2028``): text a peer chose (a station id, a
    stream name) can neither start a forged log line nor drive a terminal. Tabs stay."""
    if text.isprintable():
        return text
    return "".join(
        char if char == "\t" or unicodedata.category(char) not in _UNPRINTABLE else repr(char)[1:-1]
        for char in text
    )


_UNPRINTABLE = frozenset({"Cc", "Cf", "Zl", "Zp", "Cs"})


class EscapingFormatter(logging.Formatter):
    """Each message on one line: control characters in it are escaped (:func:`escape_control`);
    a traceback appended after it keeps its lines."""

    def formatMessage(self, record: logging.LogRecord) -> str:
        record.message = escape_control(record.message)
        return super().formatMessage(record)


class JournalFormatter(EscapingFormatter):
    """``<N>name: message``: journald reads the syslog priority from the ``<N>`` prefix."""

    def format(self, record: logging.LogRecord) -> str:
        text = super().format(record)
        priority = _PRIORITY.get(record.levelno, 6)
        return "\n".join(f"<{priority}>{line}" for line in text.splitlines())


def level_argument(text: str) -> str:
    """``--log-level``'s argparse type: a level name in any case, refused when unknown."""
    if text.upper() not in LEVELS:
        raise argparse.ArgumentTypeError(f"{text!r} is not one of {', '.join(LEVELS)}")
    return text.upper()


def setup_logging(verbosity: int = 0, level: str | None = None) -> None:
    """``-v`` → DEBUG for brasidas; ``--log-level`` wins when given."""
    chosen = level.upper() if level else ("DEBUG" if verbosity > 0 else "INFO")
    handler = logging.StreamHandler(sys.stderr)
    if os.environ.get("JOURNAL_STREAM") or os.environ.get("INVOCATION_ID"):
        handler.setFormatter(JournalFormatter("%(name)s: %(message)s"))
    else:
        handler.setFormatter(
            EscapingFormatter("%(asctime)s %(levelname)-7s %(name)s: %(message)s", "%H:%M:%S")
        )
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.WARNING if verbosity < 0 else chosen)
    if verbosity < 2:
        logging.getLogger("aiohttp.access").setLevel(logging.WARNING)
