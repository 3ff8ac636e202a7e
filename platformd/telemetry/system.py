"""System figures of the platform's computer: CPU temperature, load averages, free memory."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

SYSTEM_INFO_MAX_AGE = 1.0
"""Seconds a /proc and /sys reading is reused (they cost a few file reads)."""
THERMAL_ROOT = Path("/sys/class/thermal")
MEMINFO = Path("/proc/meminfo")
CPU_ZONE_TYPES = ("cpu-thermal", "cpu_thermal", "x86_pkg_temp", "soc_thermal", "cpu")


def system_info(thermal_root: Path = THERMAL_ROOT, meminfo: Path = MEMINFO) -> dict[str, Any]:
    """CPU temperature (null without a thermal zone), load averages, free memory."""
    try:
        load = [round(value, 2) for value in os.getloadavg()]
    except OSError:
        load = None
    memory = _meminfo(meminfo)
    return {
        "cpu_temp_c": cpu_temperature(thermal_root),
        "load": load,
        "mem_free_mb": memory.get("MemAvailable"),
        "mem_total_mb": memory.get("MemTotal"),
    }


def cpu_temperature(root: Path = THERMAL_ROOT) -> float | None:
    """The CPU's thermal zone in °C (the first zone when none is named like a CPU)."""
    try:
        zones = sorted(root.glob("thermal_zone*"))
    except OSError:
        return None
    chosen: Path | None = None
    for zone in zones:
        try:
            kind = (zone / "type").read_text().strip().lower()
        except OSError:
            continue
        if chosen is None or kind in CPU_ZONE_TYPES:
            chosen = zone
            if kind in CPU_ZONE_TYPES:
                break
    if chosen is None:
        return None
    try:
        return round(int((chosen / "temp").read_text().strip()) / 1000, 1)
    except (OSError, ValueError):
        return None


def _meminfo(path: Path) -> dict[str, float]:
    values: dict[str, float] = {}
    try:
        text = path.read_text()
    except OSError:
        return values
    for line in text.splitlines():
        name, _, rest = line.partition(":")
        if name in ("MemAvailable", "MemTotal"):
            try:
                values[name] = round(int(rest.split()[0]) / 1024, 1)
            except (ValueError, IndexError):
                continue
    return values
