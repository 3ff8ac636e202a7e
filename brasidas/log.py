"""Logging to stderr: journald-friendly priority prefixes under systemd, timestamps on a terminal."""

from __future__ import annotations

import argparse
import logging
import os
import sys

LEVELS = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")

_PRIORITY = {
    logging.CRITICAL: 2,
    logging.ERROR: 3,
    logging.WARNING: 4,
    logging.INFO: 6,
    logging.DEBUG: 7,
}


class JournalFormatter(logging.Formatter):
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
            logging.Formatter("%(asctime)s %(levelname)-7s %(name)s: %(message)s", "%H:%M:%S")
        )
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.WARNING if verbosity < 0 else chosen)
    if verbosity < 2:
        logging.getLogger("aiohttp.access").setLevel(logging.WARNING)
