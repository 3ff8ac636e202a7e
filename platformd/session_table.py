"""The open station sessions, read by every subsystem through ``ctx.sessions`` (who is calling,
from where, since when). Sessions open and close only through :meth:`SessionTable.open` and
:meth:`SessionTable.close`, which announce them: each session's SESSION_OPENED comes before
its SESSION_CLOSED, and a session never opened is never announced closed. The station
session manager (platformd.sessions) and the MAVLink endpoint's ground stations
(platformd.mavlink.service) both go through them."""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType

from brasidas.messages import SessionClosed, SessionOpened


@dataclass
class Session:
    session_id: str
    station_id: str
    peer_host: str
    session_key: bytes | None
    opened_at: float
    last_seen: float
    """The last call (heartbeat): a session silent for ``signaling.session_timeout`` ends."""
    last_velocity: float = 0.0
    """The last velocity datagram of this session accepted with its session's tag (same clock):
    the failsafe ladder takes it, like a call, as a sign that the link works; a dropped one
    (replayed, stale, held) never refreshes it."""


class SessionAlreadyOpen(ValueError):
    """A session id that is open already: opening it again would announce it twice."""


def _unannounced(event: SessionOpened | SessionClosed) -> None:
    """Without a bus (a table in a test): nobody to tell."""


@dataclass
class SessionTable:
    """Sessions by token, and the refused authentications."""

    auth_failures: int = 0
    announce: Callable[[SessionOpened | SessionClosed], None] = _unannounced
    """Where the openings and closings go (the platform's bus, set by PlatformContext)."""
    _open: dict[str, Session] = field(default_factory=dict)

    @property
    def sessions(self) -> Mapping[str, Session]:
        """The open sessions by token, read-only: they open and close through :meth:`open`
        and :meth:`close` (which announce them)."""
        return MappingProxyType(self._open)

    def get(self, session_id: str | None) -> Session | None:
        """The open session with this token, or None."""
        return self._open.get(session_id) if session_id is not None else None

    def __len__(self) -> int:
        return len(self._open)

    def open(self, session: Session) -> None:
        """Add ``session`` and announce it; raises :class:`SessionAlreadyOpen` for an id
        that is open (its first opening stands)."""
        if session.session_id in self._open:
            raise SessionAlreadyOpen(f"session {session.session_id} is open already")
        self._open[session.session_id] = session
        self.announce(SessionOpened(session.session_id, session.station_id, session.peer_host))

    def close(self, session_id: str, reason: str) -> Session | None:
        """End the session and announce it with ``reason``; None (and nothing announced)
        when no such session is open."""
        session = self._open.pop(session_id, None)
        if session is not None:
            self.announce(SessionClosed(session_id, session.station_id, reason))
        return session
