"""Telemetry: datagram size (typical and maximum) and platform CPU with sensors and telemetry on.

A real ``brasidas-platform --sim`` child process streams telemetry to a UDP socket here; the
sizes are those of the datagrams received (diagnostics off, then on). CPU is the child's
utime+stime over a 10 s window with GPS at 10 Hz, IMU at 100 Hz and telemetry at 5 Hz, no
video. Simulators not present yet are reported, and the figure covers what exists.
"""

from __future__ import annotations

import asyncio
import dataclasses
import statistics
import time
from typing import Any

from bench.support import connect_to_platform, cpu_seconds, start_platform
from brasidas.codecs.telemetry import TelemetryDecoder, TelemetryEncoder
from brasidas.config import PlatformConfig

WINDOW_S = 10.0
SIZE_SAMPLE_S = 3.0


class _Collector(asyncio.DatagramProtocol):
    def __init__(self, decoder: TelemetryDecoder) -> None:
        self.decoder = decoder
        self.sizes: list[int] = []
        self.diagnostic_sizes: list[int] = []
        self.diagnostics = False

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        if self.decoder.feed(data):
            (self.diagnostic_sizes if self.diagnostics else self.sizes).append(len(data))


def _sensor_overrides() -> tuple[list[str], list[str]]:
    """``--set`` items for GPS 10 Hz / IMU 100 Hz / telemetry 5 Hz, for the keys that exist."""
    config = PlatformConfig()
    items = ["telemetry.rate_hz=5", "navcam.enabled=false", "beacon.enabled=false"]
    present: list[str] = []
    gps_keys = {f.name for f in dataclasses.fields(config.gps)}
    for key in ("sim_rate_hz", "rate_hz", "sim_rate"):
        if key in gps_keys:
            items.append(f"gps.{key}=10")
            present.append(f"gps.{key}")
            break
    imu_keys = {f.name for f in dataclasses.fields(config.imu)}
    if "rate_hz" in imu_keys:
        items.append("imu.rate_hz=100")
        present.append("imu.rate_hz")
    return items, present


def _simulators_present() -> dict[str, bool]:
    import importlib.util

    found = {}
    for name in ("gps", "imu", "mpu6050", "ax3500"):
        try:
            found[name] = importlib.util.find_spec(f"platformd.sim.{name}") is not None
        except ImportError:
            found[name] = False
    return found


def _synthetic_full_snapshot() -> dict[str, Any]:
    """Every section filled as the finished platform will (upper bound before sims land)."""
    return {
        "mode": "teleop",
        "manual_override": True,
        "override": {"engaged": True, "station": "station-1"},
        "lights": {"main": True, "positional": True},
        "battery": {"volts": 24.37, "level": "medium", "monitor": True},
        "controller": {
            "connected": True,
            "temps_c": [41.3, 39.9],
            "amps": [12.5, 11.0],
            "internal_volts": 12.35,
        },
        "gps": {
            "fix": True,
            "latitude": 37.9838096,
            "longitude": 23.7275388,
            "altitude": 112.3,
            "speed_mps": 1.2345678,
            "course": 271.4567,
            "quality": 1,
            "satellites": 9,
            "hdop": 0.92,
            "utc": "2026-11-22T14:25:03.250000+00:00",
            "stats": {"sentences": 123456, "fixes": 12345, "bad_checksum": 12, "unknown": 3,
                      "truncated": 2, "reconnects": 0},
        },
        "attitude": {
            "roll": 1.2345678,
            "pitch": -0.3456789,
            "yaw": 271.1234567,
            "quaternion": [0.7071068, 0.0012345, -0.0023456, 0.7071068],
            "imu": {"ok": True, "temperature_c": 36.53, "samples": 1234567, "errors": 0},
        },
        "computer": {"cpu_temp_c": 48.3, "load": [0.12, 0.2, 0.25], "mem_free_mb": 612.4,
                     "mem_total_mb": 3840.0},
        "velocity_link": {"accepted": 123456, "dropped": {"malformed": 1, "bad_checksum": 2,
                          "out_of_range": 3, "out_of_order": 4, "not_engaged": 5, "not_holder": 6,
                          "bad_tag": 7}, "last_count": 123456},
        "link": {"session_rtt_ms": None, "sessions": 1, "telemetry_streams": 1},
        "streams": {"navcam": "playing", "thermal": "paused"},
        "motion": {"mode": "teleop", "deadman": False, "linear": 0.5, "angular": -0.25},
        "autonomy": None,
        "diagnostics": None,
    }  # fmt: skip


async def run() -> dict[str, Any]:
    overrides, sensor_keys = _sensor_overrides()
    from bench.support import free_port

    signaling_port = free_port()
    process = await start_platform(f"signaling.port={signaling_port}", *overrides)
    figures: dict[str, Any] = {}
    try:
        connection = await connect_to_platform(signaling_port)
        loop = asyncio.get_running_loop()
        collector = _Collector(TelemetryDecoder("brasidas-1", connection.session_key))
        transport, _ = await loop.create_datagram_endpoint(
            lambda: collector, local_addr=("127.0.0.1", 0)
        )
        try:
            port = transport.get_extra_info("sockname")[1]
            await connection.call("request_telemetry", port=port)
            await asyncio.sleep(2.0)  # start-up settles
            cpu_start, wall_start = cpu_seconds(process.pid), time.monotonic()
            received_start = len(collector.sizes)
            await asyncio.sleep(WINDOW_S)
            cpu = cpu_seconds(process.pid) - cpu_start
            wall = time.monotonic() - wall_start
            received = len(collector.sizes) - received_start
            collector.diagnostics = True
            await connection.call("issue_system_command", group=20, command=0, payload="True")
            await asyncio.sleep(SIZE_SAMPLE_S)
            report = await connection.call("get_telemetry_report")
        finally:
            transport.close()
            await connection.close()
        sizes = collector.sizes
        figures.update(
            {
                "platform_cpu_pct_one_core": round(100 * cpu / wall, 2),
                "cpu_window_s": round(wall, 1),
                "telemetry_rate_measured_hz": round(received / wall, 2),
                "datagram_bytes_typical": int(statistics.median(sizes)) if sizes else 0,
                "datagram_bytes_max": max(sizes, default=0),
                "datagram_bytes_max_with_diagnostics": max(collector.diagnostic_sizes, default=0),
                "datagrams_rejected": sum(collector.decoder.rejected.values()),
                "sections_present": ",".join(
                    sorted(name for name, value in report.items() if value not in (None, {}))
                ),
                "sensor_rate_keys_set": ",".join(sensor_keys) or "none (not in config yet)",
                "simulators_present": ",".join(
                    name for name, ok in _simulators_present().items() if ok
                )
                or "none",
                "target": "platform CPU < 5 % of one core; each datagram < 1200 bytes",
            }
        )
    finally:
        if process.returncode is None:
            process.terminate()
            try:
                await asyncio.wait_for(process.wait(), 5)
            except TimeoutError:
                process.kill()
                await process.wait()
    full = _synthetic_full_snapshot()
    encoder = TelemetryEncoder("brasidas-1", bytes(32))
    figures["datagram_bytes_all_sections_synthetic"] = max(len(d) for d in encoder.encode(full, 0))
    return figures
