"""In-process typed publish/subscribe bus.

Topics are declared once, in :mod:`brasidas.topics`, as ``Topic[T]`` keys. Delivery is
synchronous on the event loop: ``publish`` calls every subscriber before it returns, so a
subscriber must be quick (hand long work to its own actor task). A subscriber that raises is
logged and the others still get the message.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

_LOGGER = logging.getLogger(__name__)

T = TypeVar("T")

Unsubscribe = Callable[[], None]


@dataclass(frozen=True, eq=False)
class Topic(Generic[T]):
    """A named, typed bus key. Compare by identity: declare each topic once."""

    name: str
    retain: bool = field(default=False)
    """When set, the bus keeps the last message and hands it to new subscribers at once."""

    def __repr__(self) -> str:
        return f"Topic({self.name!r})"


class Bus:
    """Typed pub/sub; every method must be called from the event loop thread."""

    def __init__(self) -> None:
        self._subscribers: dict[Topic[Any], list[Callable[[Any], None]]] = {}
        self._retained: dict[Topic[Any], Any] = {}
        self.delivery_errors = 0

    def subscribe(self, topic: Topic[T], callback: Callable[[T], None]) -> Unsubscribe:
        """Call ``callback(message)`` for each message on ``topic``; returns the unsubscriber."""
        callbacks = self._subscribers.setdefault(topic, [])
        callbacks.append(callback)

        def unsubscribe() -> None:
            try:
                callbacks.remove(callback)
            except ValueError:
                pass  # already removed: unsubscribing twice is harmless

        if topic.retain and topic in self._retained:
            self._deliver(topic, callback, self._retained[topic])
        return unsubscribe

    def publish(self, topic: Topic[T], message: T) -> None:
        """Deliver ``message`` to every current subscriber of ``topic``."""
        if topic.retain:
            self._retained[topic] = message
        # Copy: a callback may unsubscribe itself while we iterate.
        for callback in tuple(self._subscribers.get(topic, ())):
            self._deliver(topic, callback, message)

    def last(self, topic: Topic[T]) -> T | None:
        """The last message published on a retained topic, or None."""
        return self._retained.get(topic)

    def subscriber_count(self, topic: Topic[Any]) -> int:
        return len(self._subscribers.get(topic, ()))

    def _deliver(self, topic: Topic[T], callback: Callable[[T], None], message: T) -> None:
        try:
            callback(message)
        except Exception:
            self.delivery_errors += 1
            _LOGGER.exception("subscriber %r of %s failed", callback, topic.name)
