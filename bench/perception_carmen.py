"""The CARMEN replay row of ``make bench perception`` (issue 30): a log made from the
simulator (:func:`platformd.sim.carmen.sample_log`: a drive round the street grid, its wheel
odometry 2 % long with a 0.01 rad/s yaw bias) replayed through the LD19 wire protocol, the
real decoder and scan assembler and the lidar odometry with the log's odometry as the prior;
the relative translational error over 1 m segments against the log's poses (mean, p95), and
the log's own odometry's for comparison; with the LD19 (12 m: far walls are not seen) and
the STL-27L (25 m). ``BENCH_CARMEN_S`` (default 120) sets the log's
length. A recorded log (``BENCH_CARMEN_FILE``) is measured the same way against its own
laser poses (those of a corrected log: the benchmark logs' are)."""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np

from brasidas.codecs.carmen import CarmenLog, parse
from brasidas.config.lidar import LidarSection
from platformd.sim.carmen import load, odometry_over_log, relative_translation_error, sample_log

SECONDS = float(os.environ.get("BENCH_CARMEN_S", "120"))


def carmen_rows() -> dict[str, Any]:
    path = os.environ.get("BENCH_CARMEN_FILE", "")
    log = load(path) if path else parse(sample_log(SECONDS))
    rows = _rows(log, "ld19") | _rows(log, "stl27l")
    return {
        "carmen_log": path or f"simulated {SECONDS:.0f} s street-grid drive",
        "carmen_lines_dropped": len(log.malformed),
        **rows,
    }


def _rows(log: CarmenLog, model: str) -> dict[str, Any]:
    config = LidarSection(enabled=True, model=model, mount_x_m=0.0, min_points=3)
    began = time.process_time()
    out = odometry_over_log(log, config)
    cpu = time.process_time() - began
    truth = [scan.pose for scan, _, _ in out]
    lidar = relative_translation_error(truth, [(p.x_m, p.y_m, p.yaw_rad) for _, p, _ in out])
    wheels = relative_translation_error(truth, [scan.odometry for scan, _, _ in out])
    registered = sum(1 for _, _, source in out if source == "lidar")
    return {
        f"carmen_{model}_scans": len(out),
        f"carmen_{model}_registered_pct": round(100 * registered / max(1, len(out)), 1),
        f"carmen_{model}_rte_1m_mean_pct": round(100 * float(np.mean(lidar)), 2) if lidar else None,
        f"carmen_{model}_rte_1m_p95_pct": round(100 * float(np.percentile(lidar, 95)), 2)
        if lidar
        else None,
        f"carmen_{model}_odometry_rte_1m_mean_pct": round(100 * float(np.mean(wheels)), 2)
        if wheels
        else None,
        f"carmen_{model}_cpu_ms_per_scan": round(1000 * cpu / max(1, len(out)), 2),
    }
