"""The scan-to-map matcher in a process of its own (:mod:`brasidas.perception.map_match`).

small_gicp holds the GIL for the whole of each call: building the map's walls (hundreds of
milliseconds for a town), and a search around an uncertain pose (45 registrations, a quarter of
a second). In a thread of the platform's process that stalls its event loop (the robot's
control) for as long. Here the walls and the matches live in a child process (started with
``forkserver``, so a daemon's threads are not forked; at the platform's own priority, unlike
the planner's: on a loaded machine a localization starved of its map is a robot that drifts);
the localizer's thread sends a scan and gets the match back later without holding the GIL.

Matches are asynchronous: :meth:`MapMatchProcess.submit` starts one (at most one in flight;
a scan arriving while one runs is not matched), :meth:`MapMatchProcess.collect` returns it
once done, with the fused pose it started from, so the localizer can carry the answer forward
by the motion since. A child that dies (killed, out of memory) is restarted on the next
submission; its walls are sent again.
"""

from __future__ import annotations

import concurrent.futures
import logging
import multiprocessing
import signal
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from brasidas.perception.map_match import MapMatch, MapMatcher
from brasidas.perception.odometry import Pose2D

_LOGGER = logging.getLogger(__name__)

_matcher: MapMatcher | None = None
"""(Child process.) The walls of the latest map."""


def _start_child() -> None:
    # Ctrl-C in the terminal reaches the whole process group: the platform stops this process
    # itself (at its shutdown), which a KeyboardInterrupt traceback here would only clutter.
    signal.signal(signal.SIGINT, signal.SIG_IGN)


def _set_walls(rings: list[NDArray[np.float64]]) -> int:
    """(Child process.) Match against ``rings`` from now on; the number of wall points."""
    global _matcher
    _matcher = MapMatcher(rings) if rings else None
    return _matcher.walls if _matcher else 0


def _match(points_xy: NDArray[np.float64], guess: Pose2D, search: bool) -> MapMatch | str:
    """(Child process.)"""
    if _matcher is None:
        return "no walls in the map"
    return _matcher.match(points_xy, guess, search=search)


@dataclass(frozen=True)
class Pending:
    """A match under way: the fused pose (x, y, yaw) at the scan it was asked for."""

    future: concurrent.futures.Future[MapMatch | str]
    start: Pose2D
    time: float


class MapMatchProcess:
    """The child process, its walls, and the one match in flight (used from one thread)."""

    def __init__(self) -> None:
        self._pool: concurrent.futures.ProcessPoolExecutor | None = None
        self._rings: list[NDArray[np.float64]] = []
        self._walls: concurrent.futures.Future[int] | None = None
        self.pending: Pending | None = None
        self.restarts = 0

    def set_walls(self, rings: list[NDArray[np.float64]]) -> None:
        """Match against ``rings`` (world frame) from the next submission on; a match in
        flight against the old walls is dropped."""
        self._rings = rings
        self.pending = None
        self._walls = self._ensure().submit(_set_walls, rings)

    def submit(
        self, points_xy: NDArray[np.float64], start: Pose2D, now: float, search: bool
    ) -> bool:
        """Start matching a scan taken at ``start``; False when one is still running (or the
        walls are still being built)."""
        if self.pending is not None or self._walls is None:
            return False
        if not self._walls.done():
            return False
        if self._walls.exception() is not None:
            self._restart(f"{self._walls.exception()}")
            return False
        try:
            future = self._ensure().submit(_match, points_xy, start, search)
        except BrokenProcessPool as err:  # it died while idle
            self._restart(str(err) or type(err).__name__)
            return False
        self.pending = Pending(future, start, now)
        return True

    def collect(self) -> tuple[Pending, MapMatch | str] | None:
        """The finished match and what it started from; None while none has finished."""
        pending = self.pending
        if pending is None or not pending.future.done():
            return None
        self.pending = None
        try:
            return pending, pending.future.result()
        except (BrokenProcessPool, OSError) as err:
            self._restart(str(err) or type(err).__name__)
            return None

    def _ensure(self) -> concurrent.futures.ProcessPoolExecutor:
        if self._pool is None:
            context = multiprocessing.get_context("forkserver")
            context.set_forkserver_preload(["platformd.map_match_process"])
            self._pool = concurrent.futures.ProcessPoolExecutor(
                1, mp_context=context, initializer=_start_child
            )
        return self._pool

    def _restart(self, why: str) -> None:
        _LOGGER.warning("map matching process failed (%s): restarting it", why)
        self.restarts += 1
        self.close()
        self.pending = None
        self._walls = self._ensure().submit(_set_walls, self._rings)

    def close(self) -> None:
        """Stop the child now, whatever it is doing: a shutdown alone lets it finish the work
        in hand (a town's walls, a search: seconds on a loaded machine), the platform's stop
        waiting on it or leaving the pool's thread behind."""
        if self._pool is not None:
            # The executor has no public way to end its workers before Python 3.14
            # (``terminate_workers``): its process table is what that one reads too.
            workers = list(self._pool._processes.values())
            self._pool.shutdown(wait=False, cancel_futures=True)
            for worker in workers:
                worker.terminate()
            self._pool = None
