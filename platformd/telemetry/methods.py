"""Signaling methods of the telemetry stream: ``request_telemetry`` and ``stop_telemetry``."""

from __future__ import annotations

import ipaddress
from typing import TYPE_CHECKING, Any

from brasidas.codecs.jsonrpc import INVALID_PARAMS, CallContext, RpcError
from brasidas.codecs.telemetry import MAX_DATAGRAM, TAG_LENGTH, VERSION

if TYPE_CHECKING:
    from platformd.context import PlatformContext
    from platformd.telemetry.stream import StreamSender

MAX_RATE_HZ = 50.0


def _ipv4(host: str) -> str:
    """An IPv4-mapped IPv6 peer address as plain IPv4 (the sending socket is AF_INET)."""
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return host
    if isinstance(address, ipaddress.IPv6Address) and address.ipv4_mapped is not None:
        return str(address.ipv4_mapped)
    return host


def allowed_host(host: str, peer_host: str) -> bool:
    """Telemetry goes only to the caller's own host or to loopback, never a third host."""
    try:
        address = ipaddress.ip_address(host)
    except ValueError:
        return False
    if address.is_loopback:
        return True
    try:
        peer = ipaddress.ip_address(_ipv4(peer_host))
    except ValueError:
        return False
    return address == peer


class TelemetryMethods:
    """Signaling methods of the telemetry stream."""

    def __init__(self, ctx: PlatformContext, sender: StreamSender) -> None:
        self.ctx = ctx
        self.sender = sender

    async def request_telemetry(
        self,
        call: CallContext,
        port: int,
        rate_hz: float | None = None,
        host: str | None = None,
    ) -> dict[str, Any]:
        """Push telemetry to ``host:port`` (default host: the caller's) until the session ends."""
        session = call.session
        peer = _ipv4(session.peer_host)
        target = peer if host is None else host
        if not isinstance(target, str) or not allowed_host(target, peer):
            raise RpcError(
                INVALID_PARAMS, "invalid params: host must be the caller's address or loopback"
            )
        if not isinstance(port, int) or isinstance(port, bool) or not 1 <= port <= 65535:
            raise RpcError(INVALID_PARAMS, "invalid params: port must be 1-65535")
        rate = self.ctx.config.telemetry.rate_hz if rate_hz is None else rate_hz
        if (
            not isinstance(rate, int | float)
            or isinstance(rate, bool)
            or not 0 < rate <= MAX_RATE_HZ
        ):
            raise RpcError(INVALID_PARAMS, f"invalid params: rate_hz must be in (0, {MAX_RATE_HZ}]")
        self.sender.start_stream(
            session.session_id, session.session_key, (target, port), float(rate)
        )
        return {
            "host": target,
            "port": port,
            "rate_hz": float(rate),
            **stream_parameters(session.session_key is not None),
        }

    async def stop_telemetry(self, call: CallContext) -> bool:
        return self.sender.stop_stream(call.session.session_id)


def stream_parameters(authenticated: bool) -> dict[str, Any]:
    return {
        "version": VERSION,
        "max_datagram": MAX_DATAGRAM,
        "auth": f"hmac-sha256-{TAG_LENGTH * 8}" if authenticated else "none",
    }
