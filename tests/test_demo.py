"""``make demo`` as the operator runs it: both daemons as processes, discovered and connected."""

from __future__ import annotations

import asyncio
import sys

from conftest import free_tcp_port, free_udp_port


async def test_demo_discovers_and_connects_then_stops_both_daemons() -> None:
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "stationd.demo",
        "--once",
        "--platform-id",
        "demo-rover",
        "--signaling-port",
        str(free_tcp_port()),
        "--api-port",
        str(free_tcp_port()),
        "--beacon-port",
        str(free_udp_port()),
        "--velocity-port",
        str(free_udp_port()),
        "--mavlink-target",
        f"127.0.0.1:{free_udp_port()}",
        "--mavlink-port",
        str(free_udp_port()),
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    out, err = await asyncio.wait_for(process.communicate(), 60)
    text = out.decode()
    assert process.returncode == 0, err.decode()
    assert "discovered platform 'demo-rover' from its beacon" in text
    assert "platform   demo-rover" in text
    assert "session" in text
    assert "Ground control station: open QGroundControl" in text


def test_example_deployment_config_loads() -> None:
    from pathlib import Path

    from brasidas.config import PlatformConfig, load_config

    path = Path(__file__).resolve().parent.parent / "deploy" / "platform.toml"
    config = load_config(PlatformConfig, path)
    assert config.beacon.destinations == ("10.144.255.255",)
    assert config.security.key_file == "/etc/brasidas/fleet.key"


def test_systemd_unit_is_notify_with_watchdog_and_restart() -> None:
    from pathlib import Path

    unit = (
        Path(__file__).resolve().parent.parent / "deploy" / "brasidas-platform.service"
    ).read_text()
    lines = {line.strip() for line in unit.splitlines()}
    assert {"Type=notify", "Restart=on-failure"} <= lines
    assert any(line.startswith("WatchdogSec=") for line in lines)
    assert any(line.startswith("ExecStart=") and "brasidas-platform" in line for line in lines)
