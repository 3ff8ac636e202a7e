"""Connections to a platform's signaling and velocity ports over loopback."""

from __future__ import annotations

import socket

from platformd.app import PlatformDaemon
from stationd.client import PlatformConnection


async def open_connection(daemon: PlatformDaemon, key: bytes | None) -> PlatformConnection:
    conn = PlatformConnection(
        daemon.config.platform.id, daemon.ctx.signaling_url, station_id="st-1", fleet_key=key
    )
    await conn.open()
    return conn


def udp_socket(host: str = "127.0.0.1") -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind((host, 0))
    return sock
