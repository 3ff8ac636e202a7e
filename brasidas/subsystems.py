"""A daemon's subsystem modules, imported before any of its actors runs.

An import on the event loop blocks it: on a loaded machine, and where no bytecode is cached
(``PYTHONDONTWRITEBYTECODE``), tenths of a second per module, so a driver's first request
timed out while the subsystems after it were still being imported (w11-dropout). A daemon
therefore imports every subsystem's module, and what the enabled parts of it will import, up
front: :func:`load` before the loop runs (the command line) and again, at no cost, at the top
of ``start()`` before its first actor.

A subsystem module may define ``preload(config)``: the imports its ``async_setup`` makes later
only under some configuration (a part switched off, an optional dependency). A preload imports
what the configuration enables and nothing else, and leaves a missing optional dependency for
the setup to report as it always has.
"""

from __future__ import annotations

import importlib
from collections.abc import Sequence
from types import ModuleType

ON_FIRST_USE: tuple[str, ...] = (
    # Standard-library modules imported on first use, in the middle of the loop's work:
    "encodings.idna",  # by the socket module, the first time a host name is given as text
    "concurrent.futures.thread",  # by concurrent.futures, with the loop's default executor
)


def load(names: Sequence[str], config: object) -> tuple[ModuleType, ...]:
    """Import the modules ``names`` in order and run each one's ``preload(config)``."""
    for name in ON_FIRST_USE:
        importlib.import_module(name)
    modules = tuple(importlib.import_module(name) for name in names)
    for module in modules:
        preload = getattr(module, "preload", None)
        if preload is not None:
            preload(config)
    return modules
