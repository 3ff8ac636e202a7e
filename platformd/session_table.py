"""The open station sessions: written by the session manager (platformd.sessions), read by
every subsystem through ``ctx.sessions`` (who is calling, from where, since when)."""

from __future__ import annotations

from dataclasses import dataclass, field


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


@dataclass
class SessionTable:
    """Sessions by token, and the refused authentications."""

    sessions: dict[str, Session] = field(default_factory=dict)
    auth_failures: int = 0

    def get(self, session_id: str | None) -> Session | None:
        """The open session with this token, or None."""
        return self.sessions.get(session_id) if session_id is not None else None

    def __len__(self) -> int:
        return len(self.sessions)
