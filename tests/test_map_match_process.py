"""Scans matched to the area map's walls in the matching process: a fit from an estimate
off by half a metre, and a child process that dies is restarted with its walls."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np

from brasidas.perception.map_match import MapMatch
from brasidas.perception.odometry import Pose2D, scan_points
from platformd.map_match_process import MapMatchProcess
from platformd.sim.drive import SimulatedDrive, loop_waypoints, street_buildings, street_grid


def _answer(maps: MapMatchProcess, timeout: float = 20.0) -> MapMatch | str | None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        done = maps.collect()
        if done is not None:
            return done[1]
        if maps.pending is None and maps.restarts:
            return None  # it died and was restarted
        time.sleep(0.01)
    raise TimeoutError


def _submitted(maps: MapMatchProcess, points: np.ndarray, start: Pose2D) -> None:
    deadline = time.monotonic() + 20.0
    while not maps.submit(points, start, 0.0, False):  # the walls are being built
        assert time.monotonic() < deadline
        time.sleep(0.01)


def test_a_scan_fits_the_walls_in_the_child_and_a_killed_child_is_restarted() -> None:
    drive = SimulatedDrive(street_grid(), loop_waypoints(), seed=4)
    for _ in range(30):
        step = drive.step()
    truth = step.truth
    points = scan_points(step.scan, step.speed_command_mps, step.gyro_rad_s)
    start = Pose2D(truth.x_m + 0.4, truth.y_m - 0.3, truth.yaw_rad + 0.02)
    maps = MapMatchProcess()
    try:
        maps.set_walls([np.asarray(b.exterior.coords) for b in street_buildings()])
        _submitted(maps, points, start)
        assert not maps.submit(points, start, 0.0, False)  # one at a time
        fit = _answer(maps)
        assert isinstance(fit, MapMatch), fit
        assert abs(fit.pose.x_m - truth.x_m) < 0.15
        assert abs(fit.pose.y_m - truth.y_m) < 0.15
        # The child dies (killed, out of memory): noticed, restarted with the same walls.
        pool = maps._pool
        assert pool is not None
        (pid,) = [p.pid for p in pool._processes.values()]  # the one worker
        os.kill(pid, signal.SIGKILL)
        # Noticed at the next submission or by its answer; restarted with the same walls.
        if maps.submit(points, start, 0.0, False):
            assert _answer(maps) is None
        assert maps.restarts == 1
        _submitted(maps, points, start)
        again = _answer(maps)
        assert isinstance(again, MapMatch), again
    finally:
        maps.close()


def test_closing_ends_a_busy_child_at_once() -> None:
    """A platform that stops does not wait on the child's work in hand, nor leave the pool's
    thread behind it (a test's leak check caught both once under load)."""
    maps = MapMatchProcess()
    try:
        busy = maps._ensure().submit(time.sleep, 30)  # stands for a slow wall build
        pool = maps._pool
        assert pool is not None
        while not busy.running():
            time.sleep(0.01)
        (worker,) = pool._processes.values()
        threads_before = set(threading.enumerate())
    finally:
        maps.close()
    worker.join(timeout=2)
    assert worker.exitcode is not None, "the child still runs"
    deadline = time.monotonic() + 2
    while any(t.is_alive() for t in threads_before if "Executor" in type(t).__name__):
        assert time.monotonic() < deadline, "the pool's thread still runs"
        time.sleep(0.01)
