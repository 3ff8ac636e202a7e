"""``brasidas-platform check`` against the simulators on ptys, a pty speaking the wrong
protocol and a port that does not exist (issue 27)."""

from __future__ import annotations

import asyncio
import json
import sys
from collections.abc import AsyncIterator
from pathlib import Path

import pytest

from brasidas import security


async def _simulator(device: str, *settings: str) -> tuple[asyncio.subprocess.Process, str]:
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "platformd",
        "simulate",
        device,
        *(arg for setting in settings for arg in ("--set", setting)),
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.DEVNULL,
    )
    assert process.stdout is not None
    path = (await asyncio.wait_for(process.stdout.readline(), 15)).decode().strip()
    assert path.startswith("/dev/pts/")
    return process, path


@pytest.fixture
async def ptys() -> AsyncIterator[dict[str, str]]:
    # The receiver at 10 Hz: three sentences well within the check's shortened listen.
    started = [await _simulator("ax3500"), await _simulator("gps", "gps.sim_rate_hz=10")]
    try:
        yield {"ax3500": started[0][1], "gps": started[1][1]}
    finally:
        for process, _ in started:
            process.terminate()
            await process.wait()


async def _check(tmp_path: Path, *settings: str) -> tuple[int, str]:
    args = [
        arg
        for setting in (
            "navcam.enabled=false",
            f"recorder.dir={tmp_path / 'recordings'}",
            "recorder.min_free_bytes=1048576",
            *settings,
        )
        for arg in ("--set", setting)
    ]
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "platformd",
        "check",
        "--json",
        # The silent port is listened to at four bauds: 0.5 s each here, not 2.5.
        "--listen",
        "0.5",
        *args,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    out, err = await asyncio.wait_for(process.communicate(), 60)
    assert process.returncode is not None
    assert out.startswith(b"["), err.decode()
    return process.returncode, out.decode()


async def test_check_passes_on_the_simulators_and_names_wrong_and_missing_devices(
    ptys: dict[str, str], tmp_path: Path
) -> None:
    security.load_or_create_key(security.default_key_path())
    code, out = await _check(
        tmp_path, f"motor.port={ptys['ax3500']}", f"gps.port={ptys['gps']}", "imu.enabled=false"
    )
    results = {result["name"]: result for result in json.loads(out)}
    assert code == 0, results
    assert results["motor"]["ok"]
    assert "AX3500 answers" in results["motor"]["detail"]
    assert results["gps"]["ok"]
    assert "NMEA" in results["gps"]["detail"]
    assert results["fleet key"]["ok"]
    assert results["clock"]["ok"]
    assert results["disk"]["ok"]
    assert results["last word"]["detail"] == "none: nothing starts by itself"

    # The ports swapped: the motor port speaks NMEA, the GPS port says nothing by itself.
    code, out = await _check(
        tmp_path,
        f"motor.port={ptys['gps']}",
        f"gps.port={ptys['ax3500']}",
        "imu.enabled=true",
        "imu.i2c_bus=199",
    )
    results = {result["name"]: result for result in json.loads(out)}
    assert code == 1
    assert not results["motor"]["ok"]
    assert "that is a GPS receiver" in results["motor"]["detail"]
    assert not results["gps"]["ok"]
    assert "no NMEA sentence in 0.5 s" in results["gps"]["detail"]
    assert results["gps"]["fix"]
    assert not results["imu"]["ok"]
    assert "/dev/i2c-199 does not exist" in results["imu"]["detail"]

    # A port that does not exist, and a key others may read.
    security.default_key_path().chmod(0o644)
    code, out = await _check(tmp_path, f"motor.port={tmp_path / 'ttyUSB9'}", "gps.enabled=false")
    results = {result["name"]: result for result in json.loads(out)}
    assert code == 1
    assert results["motor"]["detail"].endswith("ttyUSB9 does not exist")
    assert "motor.port" in results["motor"]["fix"]
    assert not results["fleet key"]["ok"]
    assert "permissions" in results["fleet key"]["detail"]
