"""What every platform subsystem gets at setup: config, bus, supervisor, RPC table, capabilities."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from brasidas.actor import Supervisor
from brasidas.bus import Bus
from brasidas.codecs.jsonrpc import Dispatcher
from brasidas.config import PlatformConfig
from platformd.session_table import Session, SessionTable


@dataclass
class PlatformContext:
    config: PlatformConfig
    bus: Bus
    supervisor: Supervisor
    rpc: Dispatcher
    """Signaling methods: ``rpc.add(name, handler)``; handlers take ``(ctx: CallContext, **params)``."""
    fleet_key: bytes | None
    """None only with --insecure."""
    signaling_url: str = ""
    """Where stations reach signaling; set once the server is bound."""
    sessions: SessionTable = field(default_factory=SessionTable)
    """The open sessions, kept by the session manager (platformd.sessions)."""
    capabilities: dict[str, Callable[[], Any]] = field(default_factory=dict)
    """Sections of the ``connect`` answer's capabilities, each computed when asked."""
    telemetry_sources: dict[str, Callable[[], Any]] = field(default_factory=dict)
    """Sections of the telemetry snapshot, each computed when a report is built."""
    diagnostics_sources: dict[str, Callable[[], Any]] = field(default_factory=dict)
    """Entries of the ``diagnostics`` section (sent only after 20.0): counters and the like."""
    sim: dict[str, Any] = field(default_factory=dict)
    """Simulated devices by name (only in --sim), for subsystems that need to reach them."""

    def session(self, session_id: str | None) -> Session | None:
        """The open session with this token, or None."""
        return self.sessions.get(session_id)

    @property
    def session_count(self) -> int:
        return len(self.sessions)
