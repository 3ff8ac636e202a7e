"""Telemetry: datagram size (typical and maximum) and platform CPU with sensors and telemetry on.

A real ``brasidas-platform --sim`` child process (simulated controller, GPS at 10 Hz, IMU at
100 Hz, telemetry at 5 Hz, no video) streams telemetry to a UDP socket here. Every datagram is
decoded through the schema (:mod:`brasidas.codecs.telemetry_schema`), so a section the schema
cannot read is counted, not sized. Sizes are those received, with diagnostics off (typical,
max) and on (max); CPU is the child's utime+stime over a 10 s window.
"""

from __future__ import annotations

import asyncio
import statistics
import time
from typing import Any

from bench.support import connect_to_platform, cpu_seconds, free_port, start_platform
from brasidas.codecs.telemetry import TelemetryDecoder
from brasidas.codecs.telemetry_schema import SCHEMA_VERSION, SectionError, snapshot_from_wire

WINDOW_S = 10.0
SIZE_SAMPLE_S = 3.0


OVERRIDES = (
    "telemetry.rate_hz=5",
    "gps.sim_rate_hz=10",
    "imu.rate_hz=100",
    "navcam.enabled=false",
    "beacon.enabled=false",
)


class _Collector(asyncio.DatagramProtocol):
    def __init__(self, decoder: TelemetryDecoder) -> None:
        self.decoder = decoder
        self.sizes: list[int] = []
        self.diagnostic_sizes: list[int] = []
        self.diagnostics = False
        self.sections: set[str] = set()
        self.section_errors: set[str] = set()
        self.unknown_sections = 0

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        for frame in self.decoder.feed(data):
            (self.diagnostic_sizes if self.diagnostics else self.sizes).append(len(data))
            snapshot, unknown = snapshot_from_wire(frame.sections)
            self.unknown_sections += len(unknown)
            for cls, value in snapshot.sections.items():
                if isinstance(value, SectionError):
                    self.section_errors.add(f"{cls.NAME}: {value.error}")
                elif value is not None:
                    self.sections.add(cls.NAME)


async def run() -> dict[str, Any]:
    signaling_port = free_port()
    process = await start_platform(f"signaling.port={signaling_port}", *OVERRIDES)
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
                "schema_version": SCHEMA_VERSION,
                "sections_present": ",".join(sorted(collector.sections)),
                "section_errors": "; ".join(sorted(collector.section_errors)) or "none",
                "unknown_sections": collector.unknown_sections,
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
    return figures
