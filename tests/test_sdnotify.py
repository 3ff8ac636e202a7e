"""systemd notify protocol against a socket the test creates: READY, watchdog pings, STOPPING."""

from __future__ import annotations

import asyncio
import os
import signal
import socket
import sys
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest
from conftest import quiet_platform_config

from brasidas.sdnotify import Notifier
from platformd import app
from platformd import cli as platform_cli
from platformd.app import PlatformDaemon
from platformd.context import PlatformContext
from platformd.sim import SimulatedDevices

Factory = Callable[..., Awaitable[PlatformDaemon]]


def notify_socket(path: str) -> socket.socket:
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind(path)
    sock.setblocking(False)
    return sock


async def receive(sock: socket.socket, timeout: float = 5.0) -> str:
    loop = asyncio.get_running_loop()
    async with asyncio.timeout(timeout):
        data = await loop.sock_recv(sock, 4096)
    return data.decode()


def test_without_notify_socket_nothing_is_sent() -> None:
    notifier = Notifier({})
    assert not notifier.enabled
    assert notifier.watchdog_interval is None
    assert notifier.ready() is False


def test_watchdog_interval_is_half_the_timeout_and_only_for_our_pid() -> None:
    env = {"NOTIFY_SOCKET": "/run/x", "WATCHDOG_USEC": "2000000"}
    assert Notifier(env).watchdog_interval == 1.0
    assert Notifier({**env, "WATCHDOG_PID": str(os.getpid())}).watchdog_interval == 1.0
    assert Notifier({**env, "WATCHDOG_PID": "1"}).watchdog_interval is None


def test_abstract_namespace_socket() -> None:
    name = f"brasidas-test-{os.getpid()}"
    sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    sock.bind("\0" + name)
    try:
        assert Notifier({"NOTIFY_SOCKET": "@" + name}).ready("up")
        assert sock.recv(100) == b"READY=1\nSTATUS=up"
    finally:
        sock.close()


async def test_platform_says_ready_pings_the_watchdog_and_says_stopping(
    tmp_path: Path, fleet_key: bytes
) -> None:
    path = str(tmp_path / "notify")
    sock = notify_socket(path)
    notifier = Notifier({"NOTIFY_SOCKET": path, "WATCHDOG_USEC": "200000"})
    daemon = PlatformDaemon(quiet_platform_config(), fleet_key, notifier)
    try:
        await daemon.start()
        messages = [await receive(sock) for _ in range(3)]
        ready = [m for m in messages if m.startswith("READY=1")]
        assert ready
        assert daemon.ctx.signaling_url in ready[0]
        assert messages.count("WATCHDOG=1") >= 2  # pinged every 0.1 s
        await daemon.stop()
        seen = []
        while "STOPPING=1" not in seen:
            seen.append(await receive(sock))
    finally:
        await daemon.stop()
        sock.close()


async def test_sigterm_says_stopping_at_once_even_during_start_up(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, fleet_key: bytes
) -> None:
    """The daemon's own signal handler sends STOPPING=1: while a subsystem is still being set
    up (held here until STOPPING has arrived), and READY=1 never follows it."""
    path = str(tmp_path / "notify")
    sock = notify_socket(path)
    monkeypatch.setenv("NOTIFY_SOCKET", path)
    monkeypatch.delenv("WATCHDOG_USEC", raising=False)
    entered, release = asyncio.Event(), asyncio.Event()
    real_start_simulators = app.start_simulators

    async def held_start_simulators(ctx: PlatformContext) -> SimulatedDevices:
        entered.set()
        await release.wait()
        return await real_start_simulators(ctx)

    monkeypatch.setattr(app, "start_simulators", held_start_simulators)
    daemon = asyncio.create_task(platform_cli.run_daemon(quiet_platform_config(), fleet_key))
    try:
        await asyncio.wait_for(entered.wait(), 10)
        assert signal.getsignal(signal.SIGTERM) is not signal.SIG_DFL  # the loop's handler
        os.kill(os.getpid(), signal.SIGTERM)
        assert await receive(sock) == "STOPPING=1"  # start-up is still held
        release.set()
        await asyncio.wait_for(daemon, 10)
        with pytest.raises(TimeoutError):
            await receive(sock, timeout=0.2)  # no READY=1 after STOPPING=1
    finally:
        release.set()
        if not daemon.done():
            daemon.cancel()
            await asyncio.gather(daemon, return_exceptions=True)
        sock.close()


async def test_platform_process_says_ready_then_stopping_on_sigterm(tmp_path: Path) -> None:
    """The real command under a notify socket, as systemd runs it (Type=notify)."""
    path = str(tmp_path / "notify")
    sock = notify_socket(path)
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "platformd",
        "--insecure",
        *("--set", "signaling.port=0", "--set", "velocity.port=0"),
        *("--set", "beacon.enabled=false", "--set", "motor.enabled=false"),
        *("--set", "gps.enabled=false", "--set", "imu.enabled=false"),
        *("--set", "navcam.enabled=false", "--set", "audio.enabled=false"),
        env={**os.environ, "NOTIFY_SOCKET": path, "WATCHDOG_USEC": "10000000"},
        stdout=asyncio.subprocess.DEVNULL,
        stderr=asyncio.subprocess.DEVNULL,
    )
    try:
        assert (await receive(sock, timeout=30)).startswith("READY=1\nSTATUS=serving http://")
        process.send_signal(signal.SIGTERM)
        after = await receive(sock)
        while after == "WATCHDOG=1":
            after = await receive(sock)
        assert after == "STOPPING=1"
        assert await asyncio.wait_for(process.wait(), 10) == 0
    finally:
        if process.returncode is None:
            process.kill()
            await process.wait()
        sock.close()


def test_unit_documentation_names_files_that_ship_with_the_project() -> None:
    """``Documentation=`` points under /opt/brasidas (the unit's install location), at files
    this repository has, not at a web address that does not exist."""
    root = Path(__file__).resolve().parents[1]
    unit = (root / "deploy" / "brasidas-platform.service").read_text()
    uris = [
        uri
        for line in unit.splitlines()
        if line.startswith("Documentation=")
        for uri in line.removeprefix("Documentation=").split()
    ]
    assert uris
    for uri in uris:
        assert uri.startswith("file:/opt/brasidas/"), uri
        assert (root / uri.removeprefix("file:/opt/brasidas/")).is_file(), uri
