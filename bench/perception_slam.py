"""The GPS-less loop row of ``make bench perception``: SLAM in the map's own frame.

The localizer (:class:`~platformd.lidar_localization.Localizer`, the platform's own) on the
simulated drive round the street grid's 160 m loop with no GPS at all (it starts in its map's
own frame), on a stepped clock: the pose error at the end of the loop (the truth carried into
the map's frame, which starts at the robot's start) with the pose graph's loop closure and
without it, the loops closed, the grid's rebuilds, and the thread CPU per keyframe (the
closure search by registration and iSAM2's update; the grid's rebuild, in its own thread, apart);
then the same with a drift put on the odometry (:data:`DRIFT_DEG_PER_M`). Seeded;
``BENCH_PERCEPTION_SLAM_LAPS`` (default 1) laps.
"""

from __future__ import annotations

import dataclasses
import math
import os
from typing import Any

from bench.support import percentiles
from brasidas.bus import Bus
from brasidas.messages import Attitude
from brasidas.perception.odometry import LidarOdometry, OdometryStep, Pose2D
from platformd.lidar_localization import Localizer
from platformd.sim.drive import MAX_SPEED_MPS, SimulatedDrive, loop_waypoints, street_grid

LAPS = int(os.environ.get("BENCH_PERCEPTION_SLAM_LAPS", "1"))
DRIFT_DEG_PER_M = 0.05
"""The second pair of rows: the odometry turned this much more per metre (a drift its scans
would not have in the street; 8° over the loop)."""


def _loop(loop_closure: bool, yaw_drift_per_m: float = 0.0) -> dict[str, Any]:
    drive = SimulatedDrive(street_grid(), loop_waypoints(), seed=2)
    localizer = Localizer(Bus(), MAX_SPEED_MPS, gps_wait_s=0.0, loop_closure=loop_closure)
    if yaw_drift_per_m:
        _drifting(localizer.odometry, yaw_drift_per_m)
    start: Pose2D | None = None
    error = 0.0
    try:
        while drive.laps < LAPS or drive.target < 1:
            step = drive.step()
            truth = step.truth
            if start is None:
                start = Pose2D(truth.x_m, truth.y_m, truth.yaw_rad)
            attitude = Attitude(1, 0, 0, 0, 0, 0, math.degrees(truth.yaw_rad), stamp=step.time)
            localizer._on_attitude(attitude)  # the IMU's yaw, as the bus would deliver it
            rate = localizer._yaw_rate(step.scan)
            localizer.process(step.scan, [], step.speed_command_mps, rate, 0.0)
            fused = localizer.fused
            if fused is not None:
                here = start.compose(Pose2D(fused.x_m, fused.y_m, fused.yaw_rad))
                error = math.hypot(here.x_m - truth.x_m, here.y_m - truth.y_m)
        # The last rebuild, if any, is let finish: the grid is part of what a keyframe costs.
        if localizer._rebuild is not None:
            localizer._rebuild[0].result()
    finally:
        localizer._worker.shutdown()
        localizer._rebuilder.shutdown()
        localizer.maps.close()
    graph = localizer.graph
    figures: dict[str, Any] = {"end_error_m": round(error, 3), "simulated_s": round(drive.now, 1)}
    if graph is not None:
        cpu = sorted(t * 1000 for t in graph.keyframe_cpu_s)
        figures |= {
            "grid_rebuild_cpu_s": round(localizer.rebuild_cpu_s, 3),
            "keyframes": len(graph.poses),
            "loop_closures": graph.closures,
            "grid_rebuilds": localizer.grid_rebuilds,
            "cpu_ms_per_keyframe": percentiles(cpu) if cpu else {},
        }
    return figures


def _drifting(odometry: LidarOdometry, yaw_per_m: float) -> None:
    """Each of the odometry's steps turned ``yaw_per_m`` more per metre: a gyro-like drift the
    street's scans do not have, so the loop is visibly open."""
    real = odometry.update

    def update(*args: Any) -> OdometryStep:
        step = real(*args)
        d = step.delta
        turned = Pose2D(d.x_m, d.y_m, d.yaw_rad + yaw_per_m * math.hypot(d.x_m, d.y_m))
        return dataclasses.replace(step, delta=turned)

    setattr(odometry, "update", update)  # noqa: B010 (a method replaced on one instance)


def slam_rows() -> dict[str, Any]:
    rows: dict[str, Any] = {}
    for label, drift in (("", 0.0), (f"_drift_{DRIFT_DEG_PER_M}deg_per_m", DRIFT_DEG_PER_M)):
        closed = _loop(True, math.radians(drift))
        opened = _loop(False, math.radians(drift))
        rows |= {
            f"gpsless_loop{label}_end_error_m_with_loop_closure": closed.pop("end_error_m"),
            f"gpsless_loop{label}_end_error_m_without": opened["end_error_m"],
            f"gpsless_loop{label}": closed
            | {"laps": LAPS, "loadavg_1m": round(os.getloadavg()[0], 2)},
        }
    return rows


if __name__ == "__main__":
    print(slam_rows())
