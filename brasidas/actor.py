"""Actor runtime: each actor is a long-lived task owned by a supervisor.

The supervisor logs a crashed actor's traceback and restarts it with capped exponential
backoff. ``stop()`` runs each actor's ``async_stop`` hook in reverse start order (so the
motor controller can command zero before the serial line closes), then cancels what is
left, all within a deadline.
"""

from __future__ import annotations

import abc
import asyncio
import contextlib
import logging
import signal
import time
from collections.abc import Callable
from typing import TypeVar

from brasidas.backoff import Backoff
from brasidas.bus import Bus, Topic, Unsubscribe

_LOGGER = logging.getLogger(__name__)
CANCEL_GRACE = 5.0
"""Seconds :meth:`Supervisor.stop` waits, past its timeout, for cancelled tasks to unwind."""

T = TypeVar("T")


class Actor:
    """Base class for a supervised actor.

    Subclasses implement :meth:`run`. Subscriptions made with :meth:`subscribe`, and whatever
    was handed to :meth:`on_remove`, are removed when the actor stops or restarts.
    """

    name: str = "actor"
    restart: bool = True
    """Restart after a crash. A normal return from ``run`` is never restarted."""
    stop_priority: int = 0
    """Higher stops first (the motor controller commands zero before anything else stops)."""

    def __init__(self, bus: Bus) -> None:
        self.bus = bus
        self._unsubscribers: list[Unsubscribe] = []

    async def run(self) -> None:
        """The actor's body. Runs until cancelled, or returns when its work is done."""
        raise NotImplementedError

    async def async_stop(self) -> None:
        """Called once, before cancellation, when the daemon shuts down. Must be quick."""

    def subscribe(self, topic: Topic[T], callback: Callable[[T], None]) -> None:
        """Subscribe for this actor's lifetime."""
        self.on_remove(self.bus.subscribe(topic, callback))

    def on_remove(self, remove: Unsubscribe) -> None:
        """Call ``remove`` when the actor stops or restarts (a command router registration,
        any other callback-returning hook-up made in ``run``)."""
        self._unsubscribers.append(remove)

    def remove_subscriptions(self) -> None:
        while self._unsubscribers:
            self._unsubscribers.pop()()


class Supervisor:
    """Owns actor tasks: starts, restarts with backoff, and stops them."""

    def __init__(
        self,
        *,
        backoff_initial: float = 0.1,
        backoff_max: float = 5.0,
        healthy_after: float = 10.0,
    ) -> None:
        self._actors: list[Actor] = []
        self._tasks: dict[Actor, asyncio.Task[None]] = {}
        self._backoff_initial = backoff_initial
        self._backoff_max = backoff_max
        self._healthy_after = healthy_after
        self._stopping = False
        self.restarts: dict[str, int] = {}

    @property
    def actors(self) -> tuple[Actor, ...]:
        return tuple(self._actors)

    def start(self, actor: Actor) -> None:
        """Start supervising ``actor``; must be called from the event loop."""
        if self._stopping:
            raise RuntimeError("supervisor is stopping")
        self._actors.append(actor)
        self._tasks[actor] = asyncio.get_running_loop().create_task(
            self._supervise(actor), name=f"actor:{actor.name}"
        )

    async def _supervise(self, actor: Actor) -> None:
        backoff = Backoff(self._backoff_initial, self._backoff_max)
        while True:
            started = time.monotonic()
            try:
                await actor.run()
            except asyncio.CancelledError:
                actor.remove_subscriptions()
                raise
            except Exception:
                actor.remove_subscriptions()
                if not actor.restart or self._stopping:
                    _LOGGER.exception("actor %s failed; not restarting", actor.name)
                    return
                if time.monotonic() - started > self._healthy_after:
                    backoff.reset()
                self.restarts[actor.name] = self.restarts.get(actor.name, 0) + 1
                delay = backoff.next()
                _LOGGER.exception("actor %s crashed; restarting in %.1f s", actor.name, delay)
                await asyncio.sleep(delay)
                continue
            actor.remove_subscriptions()
            _LOGGER.debug("actor %s finished", actor.name)
            return

    async def stop(self, timeout: float = 0.8) -> None:
        """Stop every actor: stop hooks in reverse order, then cancel, within ``timeout``; a
        cancelled task still unwinding then gets :data:`CANCEL_GRACE` more."""
        if self._stopping and not self._tasks:
            return
        self._stopping = True
        deadline = time.monotonic() + timeout
        order = sorted(reversed(self._actors), key=lambda actor: -actor.stop_priority)
        for actor in order:
            remaining = max(0.01, deadline - time.monotonic() - 0.1)
            try:
                await asyncio.wait_for(actor.async_stop(), remaining)
            except TimeoutError:
                _LOGGER.warning("actor %s did not stop in time", actor.name)
            except Exception:
                _LOGGER.exception("stop hook of actor %s failed", actor.name)
        tasks = list(self._tasks.values())
        for task in tasks:
            task.cancel("daemon stopping")
        if tasks:
            _done, pending = await asyncio.wait(
                tasks, timeout=max(0.05, deadline - time.monotonic())
            )
            if pending:
                # Cancelled, but unwinding (a loaded machine gives a task's last turns late):
                # stopped means stopped, so they get a grace; one that swallows its
                # cancellation is left behind, said.
                _LOGGER.warning(
                    "tasks %s still unwinding after stop's %.1f s",
                    ", ".join(task.get_name() for task in pending),
                    timeout,
                )
                _done, pending = await asyncio.wait(pending, timeout=CANCEL_GRACE)
            for task in pending:
                _LOGGER.warning("task %s still running after stop", task.get_name())
        for task in tasks:
            if task.done() and not task.cancelled():
                with contextlib.suppress(Exception):
                    task.result()
        for actor in self._actors:
            actor.remove_subscriptions()
        self._tasks.clear()


async def wait_forever() -> None:
    """Park an actor whose work is all in callbacks until it is cancelled."""
    await asyncio.Event().wait()


def stop_on_signals(on_signal: Callable[[], object] | None = None) -> asyncio.Event:
    """An event that SIGTERM and SIGINT (Ctrl-C) set, for a daemon or command to wind down on;
    ``on_signal`` is called at once too (e.g. to tell systemd). Off the main thread (tests run
    commands in threads) signals cannot be caught; the event is then set only by its holder."""
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()

    def handle() -> None:
        if on_signal is not None:
            on_signal()
        stop.set()

    for signum in (signal.SIGTERM, signal.SIGINT):
        with contextlib.suppress(ValueError, RuntimeError):
            loop.add_signal_handler(signum, handle)
    return stop


class Daemon(abc.ABC):
    """A daemon's lifecycle: ``start()`` sets up its actors, ``stop()`` stops them (idempotent,
    bounded), ``run()`` does both around a stop event."""

    def __init__(self) -> None:
        self.bus = Bus()
        self.supervisor = Supervisor()
        self._stopped = False

    @abc.abstractmethod
    async def start(self) -> None:
        """Set up every subsystem and start its actors."""

    async def stop(self, timeout: float = 0.9) -> None:
        if self._stopped:
            return
        self._stopped = True
        await self.supervisor.stop(timeout)

    async def run(self, stop: asyncio.Event) -> None:
        try:
            await self.start()
            await stop.wait()
        finally:
            await self.stop()
