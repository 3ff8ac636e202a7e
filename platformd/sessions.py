"""Station sessions: authenticated connect (HMAC challenge-response), heartbeats, expiry (R-17).

``challenge`` hands out a one-time nonce; ``connect`` proves knowledge of the fleet key with
HMAC(nonce, station nonce) and gets back a session token plus the platform's own proof, so both
ends authenticate each other and derive the same session key without sending it. Every session
method then carries ``session``: the token. A session ends on ``disconnect``, when its WebSocket
closes, or after ``signaling.session_timeout`` without a call — except the override holder's
while the failsafe ladder holds for it (its release step decides; the session then times out);
``SESSION_CLOSED`` tells the mode arbiter to release the manual override.
"""

from __future__ import annotations

import asyncio
import logging
import secrets
import time
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

from brasidas import __version__, security, topics
from brasidas.actor import Actor
from brasidas.codecs.beacon import boot_proof
from brasidas.codecs.commands import PAYLOAD_GROUPS
from brasidas.codecs.jsonrpc import INVALID_PARAMS, CallContext, RpcError, Unauthorized
from brasidas.messages import FailsafeStep
from brasidas.security import accept_proof, connect_proof
from platformd.authority import AuthorityWatch
from platformd.context import PlatformContext
from platformd.session_table import Session

_LOGGER = logging.getLogger(__name__)

MAX_PENDING_CHALLENGES = 256
CHALLENGE_LIFETIME = 10.0


class SessionManager(Actor):
    """Opens, refreshes and closes the sessions of ``ctx.sessions``; its ``run`` expires
    silent ones."""

    name = "sessions"

    def __init__(self, ctx: PlatformContext, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self._clock = clock
        self.table = ctx.sessions
        self._challenges: OrderedDict[str, float] = OrderedDict()

    # ------------------------------------------------------------------ lifecycle

    async def run(self) -> None:
        while True:
            await asyncio.sleep(0.1)
            self.expire()

    async def async_stop(self) -> None:
        for session_id in list(self.table.sessions):
            self.close(session_id, "shutdown")

    def expire(self) -> None:
        now = self._clock()
        timeout = self.ctx.config.signaling.session_timeout
        ladder_holds = self._ladder_holds()
        for session in list(self.table.sessions.values()):
            if now - session.last_seen > timeout:
                if session.session_id == ladder_holds:
                    continue  # the failsafe ladder decides (its release step), not the timeout
                _LOGGER.warning("session of %s timed out", session.station_id)
                self.close(session.session_id, "timeout")

    def connection_lost(self, session_id: str) -> None:
        """The session's WebSocket closed: the station is gone, the session ends — unless the
        failsafe ladder holds for it (the link was cut; the close arrives when it returns):
        then the ladder's release step decides, and the session times out after it."""
        if session_id == self._ladder_holds():
            _LOGGER.warning("connection of the override holder lost while the failsafe holds")
            return
        self.close(session_id, "connection lost")

    def _ladder_holds(self) -> str | None:
        """The override holder's session while the failsafe ladder holds for it: its expiry
        would pre-empt the ladder's release step (and ``failsafe.action = hold``), so the
        ladder owns it until it releases the override or the operator re-engages."""
        override = self.bus.last(topics.OVERRIDE_STATE)
        failsafe = self.bus.last(topics.FAILSAFE_STATE)
        if override is None or not override.engaged or failsafe is None:
            return None
        return override.session_id if failsafe.step is FailsafeStep.HOLD else None

    def close(self, session_id: str, reason: str) -> None:
        session = self.table.close(session_id, reason)
        if session is not None:
            _LOGGER.info("session of %s closed (%s)", session.station_id, reason)

    # ------------------------------------------------------------------ authorizer

    def authorize(self, call: CallContext, params: dict[str, Any]) -> None:
        """Check and strip the ``session`` token; sets ``call.session``."""
        token = params.pop("session", None)
        session = self.table.get(token) if isinstance(token, str) else None
        # A token is good only from the host that connected: one captured on the mesh and
        # replayed from elsewhere is refused (a TCP peer address cannot be spoofed blind).
        if session is None or (call.peer_host and call.peer_host != session.peer_host):
            self.table.auth_failures += 1
            raise Unauthorized("unauthorized: no valid session")
        session.last_seen = self._clock()
        call.session = session

    # ------------------------------------------------------------------ methods

    def rpc_challenge(self, call: CallContext) -> dict[str, Any]:
        """A one-time nonce for ``connect``."""
        now = self._clock()
        while self._challenges and (
            len(self._challenges) >= MAX_PENDING_CHALLENGES
            or next(iter(self._challenges.values())) < now
        ):
            self._challenges.popitem(last=False)
        nonce = secrets.token_hex(16)
        self._challenges[nonce] = now + CHALLENGE_LIFETIME
        return {
            "nonce": nonce,
            "platform_id": self.ctx.config.platform.id,
            "auth": "none" if self.ctx.fleet_key is None else "hmac-sha256",
        }

    def rpc_connect(
        self,
        call: CallContext,
        station_id: str,
        nonce: str = "",
        station_nonce: str = "",
        proof: str = "",
    ) -> dict[str, Any]:
        """Open a session; returns it with the platform's parameters and capabilities."""
        if not station_id or len(station_id) > 64 or not station_id.isprintable():
            raise RpcError(
                INVALID_PARAMS,
                "invalid params: station_id must be 1-64 printable characters (no control "
                "characters)",
            )
        key = self.ctx.fleet_key
        platform_id = self.ctx.config.platform.id
        token = secrets.token_hex(16)
        platform_proof = ""
        session_key: bytes | None = None
        if key is not None:
            expires = self._challenges.pop(nonce, None)
            expected = connect_proof(key, platform_id, station_id, nonce, station_nonce)
            if (
                expires is None
                or expires < self._clock()
                or not security.verify(expected.encode(), proof.encode())
            ):
                self.table.auth_failures += 1
                _LOGGER.warning(
                    "refused connect from %s (%s): bad proof", call.peer_host, station_id
                )
                raise Unauthorized("unauthorized: bad or expired challenge proof")
            platform_proof = accept_proof(key, platform_id, station_id, nonce, station_nonce, token)
            session_key = security.session_key(key, token, nonce, station_nonce)
        now = self._clock()
        session = Session(token, station_id, call.peer_host, session_key, now, now)
        self.table.open(session)
        call.session_opened()  # the connection is a station's now, no longer a stranger's
        if "ws" in call.extra:
            # A session opened over a WebSocket ends with it: the station is gone.
            call.extra.setdefault("on_close", []).append(lambda: self.connection_lost(token))
        _LOGGER.info("session opened by %s from %s", station_id, call.peer_host)
        boot = self.ctx.boot
        return {
            "session": token,
            "proof": platform_proof,
            # The boot number, signed for this station: it then takes beacons of this boot
            # even below one it saw (a reset counter), never of an earlier one.
            "boot": boot,
            "boot_proof": boot_proof(key, platform_id, boot, station_nonce) if key else "",
            "heartbeat_interval": self.ctx.config.signaling.heartbeat_interval,
            "session_timeout": self.ctx.config.signaling.session_timeout,
            "parameters": platform_parameters(self.ctx),
            "capabilities": capabilities(self.ctx),
        }

    def rpc_disconnect(self, call: CallContext) -> bool:
        self.close(call.session.session_id, "disconnect")
        return True

    def rpc_heartbeat(self, call: CallContext) -> dict[str, Any]:
        override = self.bus.last(topics.OVERRIDE_STATE)
        engaged = bool(override and override.engaged)
        return {
            # The platform's monotonic clock (s), which velocity packets are aged by: stations
            # estimate their offset to it from the round trip (NTP-style) and stamp $PVEL in it.
            "clock": self._clock(),
            # Held by the caller: a station streams velocity only for an override it holds.
            "manual_override": engaged
            and override is not None
            and override.session_id == call.session.session_id,
            "override_engaged": engaged,
            **self.ctx.authority.describe(call.session),
        }


def platform_parameters(ctx: PlatformContext) -> dict[str, Any]:
    config = ctx.config
    return {
        "id": config.platform.id,
        "model": config.platform.model,
        "software_version": __version__,
        "simulated": config.sim.enabled,
        "limits": {
            "max_speed_kmh": config.platform.max_speed_kmh,
            "patrol_speed_kmh": min(
                config.autonomy.cruise_speed_kmh, config.platform.max_speed_kmh
            ),
            # What one request may hold: the station refuses a bigger map or route itself.
            "max_request_bytes": config.signaling.max_request_bytes,
            "linear": [-1.0, 1.0],
            "angular": [-1.0, 1.0],
        },
    }


def capabilities(ctx: PlatformContext) -> dict[str, Any]:
    """The connect answer's capabilities: defaults, then what subsystems registered."""
    result: dict[str, Any] = {
        "streams": [],
        "velocity": velocity_endpoint(ctx),
        "telemetry": {"rate_hz": ctx.config.telemetry.rate_hz, "push": False},
        "payload_groups": sorted(
            {code.group for code in ctx.commands.codes() if code.group in PAYLOAD_GROUPS}
        ),
        "payload_commands": [
            {
                "code": str(code),
                "name": spec.name,
                "format": spec.format,
                "engagement": spec.engagement,
            }
            for code in ctx.commands.codes()
            if (spec := ctx.commands.specs.get(code)) is not None
        ],
    }
    result.update(ctx.capabilities.describe())
    return result


def velocity_endpoint(ctx: PlatformContext) -> dict[str, Any]:
    velocity = ctx.config.velocity
    return {
        "host": velocity.advertise_host or velocity.host,
        "port": ctx.velocity_port,
        "auth": "none" if ctx.fleet_key is None else "hmac-sha256-64",
    }


async def async_setup(ctx: PlatformContext) -> None:
    manager = SessionManager(ctx)
    ctx.rpc.authorizer = manager.authorize
    ctx.rpc.add("challenge", manager.rpc_challenge, session_required=False)
    ctx.rpc.add("connect", manager.rpc_connect, session_required=False)
    ctx.rpc.add("disconnect", manager.rpc_disconnect)
    ctx.rpc.add("heartbeat", manager.rpc_heartbeat)
    ctx.supervisor.start(manager)
    ctx.supervisor.start(AuthorityWatch(ctx.bus, ctx.authority))
