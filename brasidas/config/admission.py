"""The admission section both daemons' servers read: which connections they hold, how long.

One shape for the platform's signaling (``[admission]`` of ``brasidas-platform``, which adds
the caps on connections without a session) and the station's local API (``[admission]`` of
``brasidas-station``, which has no sessions: every connection is its own host's). The keys
were ``signaling.*`` and ``station.api_*`` before; :data:`PLATFORM_RENAMED` and
:data:`STATION_RENAMED` map those names to these (still accepted, with a warning).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import ClassVar

from brasidas.config.loader import Rule, above, at_least, ordered, setting


@dataclass(frozen=True)
class AdmissionSection:
    """What every connection to the daemon's server may hold, and for how long."""

    max_connections: int = setting(512, at_least(8, most=65536))
    """Connections held at once, at most (below the open-file limit less ``reserved_fds``);
    past it new ones are closed at once."""
    header_timeout: float = setting(5.0, above(0, most=300))
    """A request's headers must arrive within this (s) of their first byte."""
    body_timeout: float = setting(5.0, above(0, most=300))
    """A request's body must arrive within this (s) of its headers."""
    idle_timeout: float = setting(15.0, above(0, most=3600))
    """A connection idle between requests, or a stranger's WebSocket silent, this long (s)
    is closed."""
    write_timeout: float = setting(10.0, above(0, most=3600))
    """A connection whose unsent data has not shrunk for this long (s) is closed."""
    max_unsent_bytes: int = setting(1 << 20, at_least(65536, most=1 << 28))
    """A connection with more unsent data than this is closed (a reader that does not read;
    video frames included)."""
    reserved_fds: int = setting(128, at_least(16, most=65536))
    """File descriptors kept from connections for the daemon's own files, pipelines and
    serial lines."""
    max_batch: int = setting(100, at_least(1, most=10000))
    """Requests in a JSON-RPC batch, at most: a longer one is answered with one error."""


@dataclass(frozen=True)
class StrangerAdmissionSection(AdmissionSection):
    """The platform's signaling: also the caps on strangers (connections without a session,
    from a host that has not proved the fleet key)."""

    RULES: ClassVar[tuple[Rule, ...]] = (
        ordered("max_strangers_per_host", "max_strangers", strict=False),
        ordered("max_strangers", "max_connections", strict=False),
    )

    max_strangers: int = setting(64, at_least(1, most=65536))
    """Connections without a session held at once; past it a new one evicts the oldest
    stranger's of the address that holds the most."""
    max_strangers_per_host: int = setting(8, at_least(1, most=65536))
    """Connections without a session from one address; past it new ones are closed at once."""
    stranger_bytes_per_s: int = setting(16384, at_least(1024, most=1 << 30))
    """What one address's connections without a session may send, on average (bytes/s, a
    burst of twice as much): past it they are not read for a while. A station's handshake
    needs under 2 KiB."""


def station_admission() -> AdmissionSection:
    """The station's local API defaults: fewer connections, each a browser that may sit idle
    on a page and that is sent video frames."""
    return AdmissionSection(max_connections=256, idle_timeout=60.0, max_unsent_bytes=4 << 20)


def _renamed(old_section: str, prefix: str, section: type) -> dict[str, str]:
    return {
        f"{old_section}.{prefix}{item.name}": f"admission.{item.name}"
        for item in dataclasses.fields(section)
    }


PLATFORM_RENAMED = _renamed("signaling", "", StrangerAdmissionSection)
"""``signaling.max_connections`` and the rest: now ``admission.*``."""
STATION_RENAMED = _renamed("station", "api_", AdmissionSection)
"""``station.api_max_connections`` and the rest: now ``admission.*``."""
