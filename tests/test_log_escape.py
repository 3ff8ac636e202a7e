"""Peer-supplied text in log lines (issue 19, item 9): one message is one line, whatever a peer
put in it, and an id with control characters is refused at connect."""

from __future__ import annotations

import logging
import sys
import unicodedata
from collections.abc import Awaitable, Callable

import pytest
from conftest import quiet_platform_config
from hypothesis import given
from hypothesis import strategies as st

from brasidas.log import JournalFormatter, escape_control, setup_logging
from platformd.app import PlatformDaemon
from stationd.client import AuthenticationError, PlatformConnection

Factory = Callable[..., Awaitable[PlatformDaemon]]


def daemon_formatter() -> logging.Formatter:
    """The formatter the daemons log through (``setup_logging``'s, on a terminal)."""
    root = logging.getLogger()
    saved = root.handlers[:], root.level
    try:
        setup_logging()
        formatter = root.handlers[0].formatter
    finally:
        root.handlers[:], root.level = saved[0], saved[1]
    assert formatter is not None
    return formatter


def record(peer_text: str) -> logging.LogRecord:
    return logging.LogRecord(
        "platformd.sessions", logging.INFO, __file__, 1, "session opened by %s", (peer_text,), None
    )


def test_a_newline_in_a_station_id_cannot_forge_a_log_line() -> None:
    forged = "st-1\n12:00:00 WARNING platformd.failsafe: failsafe: normal (re-engaged)"
    line = daemon_formatter().format(record(forged))
    assert len(line.splitlines()) == 1
    assert "st-1\\n12:00:00 WARNING" in line


@given(st.text())
def test_any_peer_text_is_one_line_and_printable_text_unchanged(text: str) -> None:
    formatter = daemon_formatter()
    for fmt in (formatter, JournalFormatter("%(name)s: %(message)s")):
        line = fmt.format(record(text))
        assert len(line.splitlines()) == 1
        assert "\x1b" not in line
        assert "\r" not in line
    if text.isprintable():
        assert escape_control(text) == text


@given(st.text())
def test_escaped_text_has_no_control_character_left(text: str) -> None:
    escaped = escape_control(text)
    assert not [
        char
        for char in escaped
        if char != "\t" and unicodedata.category(char) in ("Cc", "Cf", "Zl", "Zp", "Cs")
    ]


def test_a_traceback_keeps_its_lines() -> None:
    try:
        raise ValueError("boom")
    except ValueError:
        entry = record("st\n1")
        entry.exc_info = sys.exc_info()
    text = daemon_formatter().format(entry)
    assert "st\\n1" in text.splitlines()[0]
    assert "ValueError: boom" in text


@pytest.mark.parametrize("station_id", ["st-1\nforged", "st\x1b[2J", "st\u2028x", "\x00"])
async def test_connect_refuses_a_station_id_with_control_characters(
    platform_factory: Factory, fleet_key: bytes, station_id: str
) -> None:
    daemon = await platform_factory(quiet_platform_config(), fleet_key)
    conn = PlatformConnection(
        daemon.config.platform.id,
        daemon.ctx.signaling_url,
        station_id=station_id,
        fleet_key=fleet_key,
    )
    with pytest.raises(AuthenticationError, match="printable"):
        await conn.open()
    await conn.close()
    assert not daemon.ctx.sessions.sessions
