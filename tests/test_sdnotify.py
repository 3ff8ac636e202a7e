"""systemd notify protocol against a socket the test creates: READY, watchdog pings, STOPPING."""

from __future__ import annotations

import asyncio
import os
import socket
from collections.abc import Awaitable, Callable
from pathlib import Path

from conftest import quiet_platform_config

from brasidas.sdnotify import Notifier
from platformd.app import PlatformDaemon

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
    assert not notifier.enabled and notifier.watchdog_interval is None
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
        assert ready and daemon.ctx.signaling_url in ready[0]
        assert messages.count("WATCHDOG=1") >= 2  # pinged every 0.1 s
        await daemon.stop()
        seen = []
        while "STOPPING=1" not in seen:
            seen.append(await receive(sock))
    finally:
        await daemon.stop()
        sock.close()
