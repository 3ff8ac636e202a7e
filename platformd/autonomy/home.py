"""Where the robot's home is, for the console's home marker and distance to home (issue 31):
the patrol's route's home (a mission file's), else the first GPS fix since the daemon started."""

from __future__ import annotations

from brasidas import topics
from brasidas.bus import Bus
from platformd.autonomy.patrol import PatrolActor


class Home:
    def __init__(self, bus: Bus, patrol: PatrolActor) -> None:
        self.bus = bus
        self.patrol = patrol
        self.first_fix: tuple[float, float] | None = None

    def current(self) -> tuple[float, float] | None:
        """The route's home, else the first fix (read when first asked after it came)."""
        if self.first_fix is None:
            fix = self.bus.last(topics.GPS_FIX)
            if fix is not None:
                self.first_fix = (fix.latitude, fix.longitude)
        home = self.patrol.own_route.home
        return home if home is not None else self.first_fix
