"""Maps for tests that drive in a generated town."""

from __future__ import annotations

from typing import Any

from platformd.sim.town import clear_around, town_map


def drivable_town(latitude: float, longitude: float, buildings: int) -> dict[str, Any]:
    """A town around a position, without the buildings too near it (the robot is in a street);
    without names (another test's)."""
    return clear_around(
        town_map(latitude, longitude, buildings=buildings, seed=2), latitude, longitude
    )
