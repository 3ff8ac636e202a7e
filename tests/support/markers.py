"""The suite's markers, given by what a test module uses, and its parallel workers' groups.

``browser``: drives headless Chromium (Playwright). ``netns``: builds network namespaces.
``interop``: talks to a real third-party client (MAVProxy, MAVSDK, the Foxglove client).
``slow``: any of those, or a module listed in :data:`SLOW_MODULES` (each of its tests waits
seconds of real time); ``make test-quick`` runs the rest. A test may also carry a marker
itself. A module found by what it imports marks its new tests too (no list to keep current).

Under pytest-xdist (``--dist loadgroup``) a test that uses a fixture wider than one test (a
module's network, browser or rig) runs in its module's group, on one worker, so the rig is
built once; every other test goes to whichever worker is free. The markers are registered
in pyproject.toml.
"""

from __future__ import annotations

import functools
from pathlib import Path

import pytest

HINTS = {
    "browser": ("playwright",),
    "netns": ("requires_netns", "network_fixture"),
    "interop": ("mavproxy", "mavsdk", "foxglove_client"),
}
"""Words (lower case) in a module's source that give it the marker."""

SLOW_MODULES = frozenset(
    {
        "test_authority_takeover",
        "test_demo",
        "test_failsafe",
        "test_hostile_process",
        "test_media",
        "test_media_audio",
        "test_media_station",
        "test_memory",
        "test_patrol_platform",
        "test_platform_process",
        "test_recorder",
        "test_teleop_reconnect",
    }
)
"""Modules whose tests each take seconds (``--durations`` of a whole run), beyond the ones
the hints mark."""

SHARED_SCOPES = frozenset({"module", "package", "class"})


@functools.cache
def module_markers(path: Path) -> frozenset[str]:
    """The markers the module at ``path`` gets from what it uses."""
    source = path.read_text(encoding="utf-8").lower()
    found = {name for name, words in HINTS.items() if any(word in source for word in words)}
    if found or path.stem in SLOW_MODULES:
        found.add("slow")
    return frozenset(found)


def shares_a_rig(item: pytest.Item) -> bool:
    """The test uses a fixture that outlives it (module, package or class scope)."""
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return False
    return any(
        definitions[-1].scope in SHARED_SCOPES
        for definitions in info.name2fixturedefs.values()
        if definitions
    )


def apply(items: list[pytest.Item]) -> None:
    """Mark each collected test by its module, and group the ones sharing a rig."""
    for item in items:
        path = Path(str(item.fspath))
        for name in module_markers(path):
            item.add_marker(name)
        if shares_a_rig(item) and item.get_closest_marker("xdist_group") is None:
            item.add_marker(pytest.mark.xdist_group(path.stem))
