"""The system command router (R-14): one owner per command code, answers for every code.

A subsystem registers the codes it handles with a typed async handler, usually from its
actor's ``run``, and keeps the returned callable to unregister when it stops
(``Actor.on_remove``). A second owner for a code is refused at registration. ``dispatch``
answers station-only groups, unknown codes (JSON-RPC -32602), known codes nobody here handles
("not available on this platform"), refusals by the command authority, and owners that do not
answer within ``signaling.command_timeout``; otherwise the owner's answer.

Who may send what (the session holding the manual override, observers refused) is decided in
one place: the ``authorize`` hook, called with the command and its session before any owner
sees it. Until command authority exists it lets everything through.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable
from dataclasses import dataclass

from brasidas.bus import Unsubscribe
from brasidas.codecs.commands import STATION_ONLY_GROUPS, CommandCode, describe
from brasidas.codecs.jsonrpc import INVALID_PARAMS, RpcError
from brasidas.messages import CommandResult
from platformd.session_table import Session

_LOGGER = logging.getLogger(__name__)


@dataclass(frozen=True)
class SystemCommand:
    """A system command from a station, as its owner's handler receives it."""

    code: CommandCode
    payload: str
    session: Session | None
    """The calling station's session; None for a command issued on the platform itself."""

    @property
    def session_id(self) -> str | None:
        return self.session.session_id if self.session is not None else None


CommandHandler = Callable[[SystemCommand], Awaitable[CommandResult]]
"""An owner's handler: answers with a CommandResult (it may wait, e.g. on a device)."""

Authorize = Callable[[SystemCommand], str | None]
"""Command authority: the reason to refuse ``command``, or None to let it through."""


def allow_all(command: SystemCommand) -> str | None:
    """The authority hook until command authority exists: every session may send anything."""
    return None


@dataclass(frozen=True)
class CommandSpec:
    """What a payload's command is, for ``connect``'s capabilities and for command authority."""

    name: str
    format: str
    """Its payload string, e.g. ``az=<deg>,el=<deg>``."""
    engagement: bool = False
    """Engages a target (R-0.5): only from the override holder under manual override."""


class DuplicateCommandError(ValueError):
    """A code registered while another owner holds it."""


@dataclass(frozen=True)
class _Registration:
    owner: str
    handler: CommandHandler


class CommandRouter:
    """Routes each system command to the one subsystem that registered its code."""

    def __init__(self, timeout: float, authorize: Authorize = allow_all) -> None:
        self.timeout = timeout
        """Seconds an owner has to answer (``signaling.command_timeout``)."""
        self.authorize = authorize
        self._owners: dict[CommandCode, _Registration] = {}
        self.specs: dict[CommandCode, CommandSpec] = {}
        """Descriptions of registered payload commands (``register(..., specs=)``)."""
        self.counters: dict[str, int] = dict.fromkeys(
            ("dispatched", "unknown", "unavailable", "refused", "timeouts", "failures"), 0
        )
        self.on_answered: Callable[[SystemCommand, CommandResult], None] | None = None
        """Told of every command with an owner and its answer (the context publishes it)."""

    def register(
        self,
        owner: str,
        handlers: dict[CommandCode, CommandHandler],
        specs: dict[CommandCode, CommandSpec] | None = None,
    ) -> Unsubscribe:
        """Route ``handlers``' codes to ``owner``; returns the callable that unregisters them.

        Raises DuplicateCommandError (nothing registered) if another owner holds one of the
        codes, ValueError for a station-only group.
        """
        for code in handlers:
            if code.group in STATION_ONLY_GROUPS:
                raise ValueError(f"{code}: group {code.group} is station-only")
            held = self._owners.get(code)
            if held is not None:
                raise DuplicateCommandError(f"{code} is already handled by {held.owner}")
        mine = {code: _Registration(owner, handler) for code, handler in handlers.items()}
        self._owners.update(mine)
        self.specs.update(specs or {})

        def unregister() -> None:
            for code, registration in mine.items():
                if self._owners.get(code) is registration:
                    del self._owners[code]
                    self.specs.pop(code, None)

        return unregister

    def spec_name(self, code: CommandCode) -> str | None:
        """``turret fire (100.1)``-like name of a registered payload command, or None."""
        spec = self.specs.get(code)
        registration = self._owners.get(code)
        if spec is None or registration is None:
            return None
        return f"{registration.owner} {spec.name} ({code})"

    def is_engagement(self, code: CommandCode) -> bool:
        """True for a command registered as an engagement (the trigger)."""
        spec = self.specs.get(code)
        return spec is not None and spec.engagement

    def owner(self, code: CommandCode) -> str | None:
        """Who handles ``code``, or None."""
        registration = self._owners.get(code)
        return registration.owner if registration is not None else None

    def codes(self) -> list[CommandCode]:
        """Every code that has an owner, in order."""
        return sorted(self._owners, key=lambda code: (code.group, code.command))

    async def dispatch(
        self, code: CommandCode, payload: str, session: Session | None
    ) -> CommandResult:
        """The answer to one command; raises RpcError(-32602) for a code nobody knows."""
        if code.group in STATION_ONLY_GROUPS:
            return CommandResult(False, f"group {code.group} is station-only")
        registration = self._owners.get(code)
        if registration is None:
            description = describe(code)
            if description is None:
                self.counters["unknown"] += 1
                raise RpcError(INVALID_PARAMS, f"unknown command code {code}")
            self.counters["unavailable"] += 1
            return CommandResult(False, f"{code} ({description}) is not available on this platform")
        command = SystemCommand(code, payload, session)
        result = await self._answer(command, registration)
        if self.on_answered is not None:
            self.on_answered(command, result)
        return result

    async def _answer(self, command: SystemCommand, registration: _Registration) -> CommandResult:
        code, session = command.code, command.session
        refusal = self.authorize(command)
        if refusal is not None:
            self.counters["refused"] += 1
            _LOGGER.warning(
                "%s refused for %s: %s",
                code,
                session.station_id if session is not None else "the platform",
                refusal,
            )
            return CommandResult(False, refusal)
        self.counters["dispatched"] += 1
        try:
            return await asyncio.wait_for(registration.handler(command), self.timeout)
        except TimeoutError:
            self.counters["timeouts"] += 1
            _LOGGER.warning(
                "%s not answered by %s in %.1f s", code, registration.owner, self.timeout
            )
            return CommandResult(
                False, f"{code} not answered by {registration.owner} in {self.timeout:g} s"
            )
        except RpcError:
            raise
        except Exception as err:
            self.counters["failures"] += 1
            _LOGGER.exception("%s: handler of %s failed", code, registration.owner)
            return CommandResult(False, f"{code} failed in {registration.owner}: {err}")
