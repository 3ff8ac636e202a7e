"""The system command router on its own: one owner per code, every code answered, the
authority hook before any owner, the timeout, registrations that end with their actor."""

from __future__ import annotations

import asyncio

import pytest

from brasidas.actor import Actor, Supervisor
from brasidas.bus import Bus
from brasidas.codecs.commands import (
    BATTERY_MONITOR,
    MAIN_LIGHTS,
    MANUAL_OVERRIDE,
    CommandCode,
)
from brasidas.codecs.jsonrpc import INVALID_PARAMS, RpcError
from brasidas.messages import CommandResult
from platformd.commands import CommandRouter, DuplicateCommandError, SystemCommand
from platformd.session_table import Session

SESSION = Session("token-1", "station-1", "127.0.0.1", None, 0.0, 0.0)


def answering(result: CommandResult, seen: list[SystemCommand] | None = None):  # type: ignore[no-untyped-def]
    async def handler(command: SystemCommand) -> CommandResult:
        if seen is not None:
            seen.append(command)
        return result

    return handler


async def test_the_owner_answers_with_the_command_and_its_session() -> None:
    router = CommandRouter(timeout=1.0)
    seen: list[SystemCommand] = []
    router.register("lights", {MAIN_LIGHTS: answering(CommandResult(True, result=1), seen)})
    assert await router.dispatch(MAIN_LIGHTS, "ON", SESSION) == CommandResult(True, result=1)
    assert seen == [SystemCommand(MAIN_LIGHTS, "ON", SESSION)]
    assert seen[0].session_id == "token-1"
    assert router.owner(MAIN_LIGHTS) == "lights"
    assert router.codes() == [MAIN_LIGHTS]


async def test_a_second_owner_is_refused_at_registration_and_nothing_of_it_is_kept() -> None:
    router = CommandRouter(timeout=1.0)
    router.register("motor", {MAIN_LIGHTS: answering(CommandResult(True))})
    with pytest.raises(DuplicateCommandError, match=r"10\.6 is already handled by motor"):
        router.register(
            "gpio",
            {
                BATTERY_MONITOR: answering(CommandResult(True)),
                MAIN_LIGHTS: answering(CommandResult(False)),
            },
        )
    assert router.owner(BATTERY_MONITOR) is None  # all or nothing
    with pytest.raises(ValueError, match="station-only"):
        router.register("notifier", {CommandCode(90, 1): answering(CommandResult(True))})


async def test_unregistering_frees_the_code_and_touches_nobody_else() -> None:
    router = CommandRouter(timeout=1.0)
    unregister = router.register("motor", {MAIN_LIGHTS: answering(CommandResult(True))})
    unregister()
    answer = await router.dispatch(MAIN_LIGHTS, "ON", None)
    assert not answer.accepted
    assert answer.reason == "10.6 (main lights) is not available on this platform"
    router.register("gpio", {MAIN_LIGHTS: answering(CommandResult(True, result="gpio"))})
    unregister()  # twice, after someone else took the code: harmless
    assert (await router.dispatch(MAIN_LIGHTS, "ON", None)).result == "gpio"


async def test_every_code_is_answered() -> None:
    router = CommandRouter(timeout=1.0)
    answer = await router.dispatch(CommandCode(91, 0), "", SESSION)
    assert not answer.accepted
    assert "station-only" in answer.reason
    with pytest.raises(RpcError) as err:
        await router.dispatch(CommandCode(42, 1), "", SESSION)
    assert err.value.code == INVALID_PARAMS
    assert "unknown command code 42.1" in err.value.message
    answer = await router.dispatch(CommandCode(104, 2), "", SESSION)
    assert not answer.accepted
    assert "payload group 104" in answer.reason
    assert router.counters["unknown"] == 1
    assert router.counters["unavailable"] == 1


async def test_payload_groups_100_to_110_are_registrable() -> None:
    router = CommandRouter(timeout=1.0)
    handlers = {
        CommandCode(group, 1): answering(CommandResult(True, result=group))
        for group in range(100, 111)
    }
    router.register("turret", handlers)
    for group in range(100, 111):
        assert (await router.dispatch(CommandCode(group, 1), "", SESSION)).result == group


async def test_a_silent_owner_is_answered_for_at_the_timeout() -> None:
    router = CommandRouter(timeout=0.05)
    release = asyncio.Event()

    async def sleepy(command: SystemCommand) -> CommandResult:
        await release.wait()
        return CommandResult(True)

    router.register("sleepy", {BATTERY_MONITOR: sleepy})
    answer = await router.dispatch(BATTERY_MONITOR, "ON", SESSION)
    assert answer == CommandResult(False, "20.4 not answered by sleepy in 0.05 s")
    assert router.counters["timeouts"] == 1


async def test_a_failing_owner_is_an_answer_not_a_crash() -> None:
    router = CommandRouter(timeout=1.0)

    async def broken(command: SystemCommand) -> CommandResult:
        raise KeyError("oops")

    router.register("broken", {MAIN_LIGHTS: broken})
    answer = await router.dispatch(MAIN_LIGHTS, "ON", SESSION)
    assert not answer.accepted
    assert "failed in broken" in answer.reason
    assert router.counters["failures"] == 1


async def test_authority_is_asked_first_with_the_calling_session() -> None:
    """The hook command authority (issue 13) fills: it sees the command and its session
    before any owner, and a refusal never reaches the owner."""
    seen: list[SystemCommand] = []
    asked: list[SystemCommand] = []

    def authorize(command: SystemCommand) -> str | None:
        asked.append(command)
        if command.session is None or command.session.station_id != "holder":
            return f"observer: control is held by holder ({command.code})"
        return None

    router = CommandRouter(timeout=1.0, authorize=authorize)
    router.register("mode", {MANUAL_OVERRIDE: answering(CommandResult(True), seen)})
    answer = await router.dispatch(MANUAL_OVERRIDE, "ON", SESSION)
    assert answer == CommandResult(False, "observer: control is held by holder (10.0)")
    assert asked == [SystemCommand(MANUAL_OVERRIDE, "ON", SESSION)]
    assert seen == []
    holder = Session("token-2", "holder", "127.0.0.1", None, 0.0, 0.0)
    assert (await router.dispatch(MANUAL_OVERRIDE, "ON", holder)).accepted
    assert [command.session for command in seen] == [holder]
    assert router.counters["refused"] == 1
    # Codes nobody handles are answered before authority is asked.
    asked.clear()
    await router.dispatch(MAIN_LIGHTS, "ON", SESSION)
    assert asked == []


async def test_the_default_authority_lets_everything_through() -> None:
    router = CommandRouter(timeout=1.0)
    router.register("mode", {MANUAL_OVERRIDE: answering(CommandResult(True))})
    assert (await router.dispatch(MANUAL_OVERRIDE, "ON", None)).accepted
    assert (await router.dispatch(MANUAL_OVERRIDE, "ON", SESSION)).accepted


class _Lights(Actor):
    """Registers 10.6 when it runs; crashes on its first run."""

    name = "lights"

    def __init__(self, bus: Bus, router: CommandRouter) -> None:
        super().__init__(bus)
        self.router = router
        self.runs = 0
        self.running = asyncio.Event()

    async def run(self) -> None:
        self.runs += 1
        self.on_remove(self.router.register(self.name, {MAIN_LIGHTS: self._command}))
        if self.runs == 1:
            raise RuntimeError("first run crashes")
        self.running.set()
        await asyncio.Event().wait()

    async def _command(self, command: SystemCommand) -> CommandResult:
        return CommandResult(True, result=self.runs)


async def test_a_registration_lives_as_long_as_its_actor() -> None:
    router = CommandRouter(timeout=1.0)
    supervisor = Supervisor(backoff_initial=0.01)
    actor = _Lights(Bus(), router)
    supervisor.start(actor)
    try:
        await asyncio.wait_for(actor.running.wait(), 5)
        # Restarted after the crash: registered again, no duplicate with its earlier self.
        assert (await router.dispatch(MAIN_LIGHTS, "ON", None)).result == 2
    finally:
        await supervisor.stop()
    assert router.owner(MAIN_LIGHTS) is None
