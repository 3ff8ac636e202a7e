"""Command authority (issue 13): one controller, observers, explicit takeover.

Exactly one session holds *control*: the manual override, the velocity stream, lights, stream
pause and framerate, payload and autonomy commands — every system command except the few an
observer may send (:data:`OBSERVER_CODES`: starting and stopping its own copy of the streams).
The first session to send a control command while nobody holds control claims it; it keeps it
until its session ends or another station takes it with ``force`` (MOVRD ``state=on,force=1``,
``brasidas-station movrd ID on --force``); the same station (id and host) on a new session — it
lost its old one with the link — takes it back without force. A takeover releases the previous holder's override
before the new holder's request runs, and tells it (``CONTROL_STATE``; its next heartbeat
answer says who holds control).

Decided here and nowhere else: the command router calls :meth:`Authority.authorize` before any
owner sees a command, and control RPC methods are registered through :meth:`Authority.guard`.
"""

from __future__ import annotations

import functools
import json
import logging
from collections.abc import Awaitable, Callable
from typing import Any

from brasidas import topics
from brasidas.actor import Actor, wait_forever
from brasidas.bus import Bus
from brasidas.codecs.commands import (
    MANUAL_OVERRIDE,
    OBSERVER_CODES,
    CommandCode,
    PayloadError,
    describe,
    parse_payload,
    parse_switch,
)
from brasidas.codecs.jsonrpc import CONTROL_REFUSED, CallContext, RpcError
from brasidas.messages import CommandReceived, ControlState, FailsafeStep, SessionClosed
from platformd.commands import SystemCommand
from platformd.session_table import Session, SessionTable

_LOGGER = logging.getLogger(__name__)
PAYLOAD_KEPT = 4096
"""A control method's parameters are recorded up to this many characters."""
ITEMS_KEPT = 64
"""Of a list in those parameters, this many items are recorded (then a count of the rest)."""


def _shortened(value: Any, depth: int = 0) -> Any:
    """``value`` with every list cut to :data:`ITEMS_KEPT` items: what is recorded of it."""
    if depth > 32:
        return "..."
    if isinstance(value, dict):
        return {key: _shortened(item, depth + 1) for key, item in value.items()}
    if isinstance(value, list):
        kept = [_shortened(item, depth + 1) for item in value[:ITEMS_KEPT]]
        return kept + ([f"... {len(value) - ITEMS_KEPT} more"] if len(value) > ITEMS_KEPT else [])
    return value


class Authority:
    """Who holds control; the one place that says whether a session may command."""

    def __init__(
        self,
        bus: Bus,
        sessions: SessionTable,
        is_engagement: Callable[[CommandCode], bool] = lambda code: False,
    ) -> None:
        self.bus = bus
        self.sessions = sessions
        self.is_engagement = is_engagement
        self.command_name: Callable[[CommandCode], str | None] = lambda code: None
        """A registered payload command's name (set with the router)."""
        self.controller: Session | None = None
        self.counters: dict[str, int] = dict.fromkeys(
            ("claims", "takeovers", "reclaims", "refused", "engagement_refused"), 0
        )

    @property
    def station_id(self) -> str | None:
        """The controlling station, or None."""
        return self.controller.station_id if self.controller is not None else None

    def holds(self, session: Session | None) -> bool:
        """True when ``session`` holds control (the platform itself always may)."""
        return session is None or (
            self.controller is not None and self.controller.session_id == session.session_id
        )

    def refusal(self, session: Session | None, what: str, *, force: bool = False) -> str | None:
        """None (claiming free control, or taking it with ``force``) or the reason to refuse."""
        if session is None or self.holds(session):
            return None
        if self.controller is None:
            self._set(session, "claimed")
            self.counters["claims"] += 1
            return None
        if force:
            self.counters["takeovers"] += 1
            self._set(session, f"taken by {session.station_id}")
            return None
        if _same_station(self.controller, session):
            # The station came back on a new session (its old one was lost with the link):
            # it takes its own control back without force; its old override is released.
            self.counters["reclaims"] += 1
            self._set(session, f"reclaimed by {session.station_id} on a new session")
            return None
        self.counters["refused"] += 1
        return f"{what} refused: control held by station {self.controller.station_id}"

    def authorize(self, command: SystemCommand) -> str | None:
        """The command router's hook: observers may only start and stop their own streams."""
        if command.code in OBSERVER_CODES:
            return None
        code = command.code
        what = self.command_name(code) or describe(code) or str(code)
        refusal = self.refusal(command.session, what, force=_forced(command.code, command.payload))
        if refusal is None and self.is_engagement(command.code):
            refusal = self.engagement_refusal(command.session, what)
            if refusal is not None:
                self.counters["engagement_refused"] += 1
        return refusal

    def engagement_refusal(self, session: Session | None, what: str) -> str | None:
        """R-0.5: engagement only under manual override, from its holder, with no failsafe
        step in progress. The reason, or None."""
        override = self.bus.last(topics.OVERRIDE_STATE)
        if override is None or not override.engaged:
            return f"{what} refused: engagement only under manual override (Autonomous Mode)"
        if session is None or override.session_id != session.session_id:
            return f"{what} refused: only the override holder ({override.station_id}) engages"
        failsafe = self.bus.last(topics.FAILSAFE_STATE)
        if failsafe is not None and failsafe.step is not FailsafeStep.NORMAL:
            return f"{what} refused: failsafe {failsafe.step.value} (re-engage the override)"
        return None

    def guard(
        self, what: str, handler: Callable[..., Awaitable[Any]]
    ) -> Callable[..., Awaitable[Any]]:
        """A control RPC method: refused (RpcError CONTROL_REFUSED) to an observer."""

        @functools.wraps(handler)
        async def guarded(call: CallContext, **params: Any) -> Any:
            reason = self.refusal(call.session, what)
            if reason is not None:
                self._received(what, params, call.session, False, reason)
                raise RpcError(CONTROL_REFUSED, reason)
            try:
                result = await handler(call, **params)
            except RpcError as err:
                self._received(what, params, call.session, False, err.message)
                raise
            self._received(what, params, call.session, True)
            return result

        return guarded

    def _received(
        self, what: str, params: dict[str, Any], session: Session | None, ok: bool, reason: str = ""
    ) -> None:
        """Tell the bus (the recorder) who sent which control method and how it went."""
        try:
            # Long lists cut first: a 3 MB map is not serialized on the loop to keep 4 KiB.
            payload = json.dumps(_shortened(params), default=str)[:PAYLOAD_KEPT]
        except (TypeError, ValueError):
            payload = "<unprintable>"
        self.bus.publish(
            topics.COMMAND_RECEIVED,
            CommandReceived(
                "rpc",
                what,
                payload,
                session.session_id if session else None,
                session.station_id if session else None,
                ok,
                reason,
            ),
        )

    def release(self, session_id: str, reason: str) -> None:
        """The controller's session ended: control is free."""
        if self.controller is not None and self.controller.session_id == session_id:
            self._set(None, reason)

    def describe(self, session: Session | None) -> dict[str, Any]:
        """For the heartbeat answer: who holds control and whether it is the caller."""
        return {"controller": self.station_id, "control": self.holds(session)}

    def _set(self, session: Session | None, reason: str) -> None:
        previous = self.controller
        self.controller = session
        level = logging.WARNING if previous is not None and session is not None else logging.INFO
        _LOGGER.log(level, "control: %s (%s)", session.station_id if session else "nobody", reason)
        self.bus.publish(
            topics.CONTROL_STATE,
            ControlState(
                session.session_id if session else None,
                session.station_id if session else None,
                previous.station_id if previous else None,
                reason,
            ),
        )


def _same_station(holder: Session, session: Session) -> bool:
    """``session`` is a later session of the station holding control, from the same host."""
    return holder.station_id == session.station_id and holder.peer_host == session.peer_host


def _forced(code: CommandCode, payload: str) -> bool:
    """MOVRD ``state=on,force=1``: take control (only to engage)."""
    if code != MANUAL_OVERRIDE or "=" not in payload:
        return False
    try:
        values = parse_payload(payload)
        return parse_switch(values.get("force", "no") or "yes") and parse_switch(payload)
    except PayloadError:
        return False


class AuthorityWatch(Actor):
    """Frees control when its holder's session ends."""

    name = "authority"

    def __init__(self, bus: Bus, authority: Authority) -> None:
        super().__init__(bus)
        self.authority = authority

    async def run(self) -> None:
        self.subscribe(topics.SESSION_CLOSED, self._on_session_closed)
        self.bus.publish(topics.CONTROL_STATE, ControlState())
        await wait_forever()

    def _on_session_closed(self, event: SessionClosed) -> None:
        self.authority.release(event.session_id, f"session of {event.station_id} ended")
