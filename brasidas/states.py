"""Connection-like state as an explicit enum with the transitions it may take (as
aioesphomeapi's ``ConnectionState``): a MAVLink link, an upload, an admission slot, the
planner process. A transition not in the table is a bug, raised as
:class:`InvalidTransition`, never a state quietly taken.
"""

from __future__ import annotations

import enum
from collections.abc import Mapping
from typing import Generic, TypeVar

S = TypeVar("S", bound=enum.Enum)


class InvalidTransition(RuntimeError):
    """A state change its table does not allow."""


class Transitions(Generic[S]):
    """The allowed next states of each state (a state missing from the table is final)."""

    __slots__ = ("allowed", "name")

    def __init__(self, name: str, allowed: Mapping[S, frozenset[S]]) -> None:
        self.name = name
        self.allowed = allowed

    def check(self, current: S, new: S) -> S:
        """``new``, if ``current`` may become it; else raises :class:`InvalidTransition`."""
        if new not in self.allowed.get(current, frozenset()):
            raise InvalidTransition(f"{self.name}: {current.name} → {new.name} is not allowed")
        return new

    def final(self, state: S) -> bool:
        """No way out of ``state``."""
        return not self.allowed.get(state)
