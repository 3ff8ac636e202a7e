"""The typed registry of telemetry sections: one source per schema section type.

A subsystem registers the function that builds its section
(``ctx.telemetry.register(Motion, arbiter.motion_section)``); the types make mypy check that
the function builds that section. :meth:`TelemetrySources.build` calls every source: one that
raises becomes that section's :class:`~brasidas.codecs.telemetry_schema.SectionError`, is
counted and logged (once, then at most every :data:`LOG_EVERY_S` per section), and the other
sections go on.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping

from brasidas.codecs.telemetry_schema import S, Section, SectionError, SectionValue

_LOGGER = logging.getLogger(__name__)

LOG_EVERY_S = 60.0
"""A section failing on every snapshot is logged at most this often."""


class TelemetrySources:
    """Section sources by schema type, and the counters the diagnostics section carries."""

    def __init__(self, *, clock: Callable[[], float] = time.monotonic) -> None:
        self._sources: dict[type[Section], Callable[[], Section | None]] = {}
        self.counters: dict[str, Callable[[], Mapping[str, int]]] = {}
        """Counters of a subsystem by its name, for the diagnostics section (20.0)."""
        self.errors: dict[str, int] = {}
        """Failures by section name since start."""
        self._clock = clock
        self._logged: dict[str, tuple[float, int]] = {}

    def register(self, section: type[S], source: Callable[[], S | None]) -> None:
        """Build ``section`` with ``source``; one owner per section (a second is refused)."""
        if section in self._sources:
            raise ValueError(f"telemetry section {section.NAME!r} already has a source")
        self._sources[section] = source

    def add_counters(self, name: str, counters: Callable[[], Mapping[str, int]]) -> None:
        """Report ``counters()`` as ``name`` in the diagnostics section."""
        if name in self.counters:
            raise ValueError(f"diagnostics counters {name!r} already registered")
        self.counters[name] = counters

    def __contains__(self, section: type[Section]) -> bool:
        return section in self._sources

    def build_one(self, section: type[S]) -> S | SectionError | None:
        """One section, built now (None: no source, or it has nothing to report)."""
        source = self._sources.get(section)
        if source is None:
            return None
        value = self._call(section, source)
        assert value is None or isinstance(value, section | SectionError)
        return value

    def build(self) -> dict[type[Section], SectionValue]:
        """Every section, built now, in registration order."""
        return {section: self._call(section, source) for section, source in self._sources.items()}

    def _call(self, section: type[Section], source: Callable[[], Section | None]) -> SectionValue:
        try:
            value = source()
            if value is not None and not isinstance(value, section):
                raise TypeError(f"source returned {type(value).__name__}")
        except Exception as err:
            self._failed(section.NAME, err)
            return SectionError(f"{type(err).__name__}: {err}")
        return value

    def _failed(self, name: str, err: Exception) -> None:
        self.errors[name] = self.errors.get(name, 0) + 1
        now = self._clock()
        last = self._logged.get(name)
        if last is None:
            _LOGGER.error("telemetry section %s failed", name, exc_info=err)
            self._logged[name] = (now, self.errors[name])
        elif now - last[0] >= LOG_EVERY_S:
            _LOGGER.error(
                "telemetry section %s failed %d more times: %s: %s",
                name,
                self.errors[name] - last[1],
                type(err).__name__,
                err,
            )
            self._logged[name] = (now, self.errors[name])
