"""Shared fixtures. Every test fails if it leaves tasks running (STYLE.md §9)."""

from __future__ import annotations

import asyncio
import logging
import os
import socket
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from pathlib import Path

import pytest

from brasidas.config import PlatformConfig, load_config
from platformd.app import PlatformDaemon


@pytest.fixture(autouse=True)
def _isolated_state(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Keep fleet keys and other state out of the real home directory."""
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    yield


@pytest.fixture(autouse=True)
def _restore_logging() -> Iterator[None]:
    """A CLI's ``setup_logging`` replaces the root handlers with one bound to this test's
    captured stderr; left in place it would write to a closed file in every later test."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


@pytest.fixture(autouse=True)
async def verify_no_lingering_tasks() -> AsyncIterator[None]:
    before = asyncio.all_tasks()
    yield
    # Give cancelled tasks one turn of the loop to finish unwinding.
    await asyncio.sleep(0)
    lingering = [
        task
        for task in asyncio.all_tasks() - before
        if not task.done() and task is not asyncio.current_task()
    ]
    for task in lingering:
        task.cancel()
    assert not lingering, f"test left tasks running: {[t.get_name() for t in lingering]}"


async def wait_until(predicate: Callable[[], bool], timeout: float = 5.0) -> None:
    """Poll ``predicate`` until true; fails the test after a generous ``timeout``."""

    async def poll() -> None:
        while not predicate():
            await asyncio.sleep(0.01)

    await asyncio.wait_for(poll(), timeout)


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.fixture
def fleet_key() -> bytes:
    return os.urandom(32)


def quiet_platform_config(*overrides: str) -> PlatformConfig:
    """A platform config for in-process tests: ephemeral ports, no hardware, no beacons.

    Later ``overrides`` win, so a test can switch on just what it exercises.
    """
    defaults = [
        "signaling.port=0",
        "velocity.port=0",
        "beacon.enabled=false",
        "motor.enabled=false",
        "gps.enabled=false",
        "imu.enabled=false",
        "navcam.enabled=false",
        "audio.enabled=false",
    ]
    return load_config(PlatformConfig, None, [*defaults, *overrides])


@pytest.fixture
async def platform_factory() -> AsyncIterator[Callable[..., Awaitable[PlatformDaemon]]]:
    """Start in-process platforms; all are stopped after the test."""
    started: list[PlatformDaemon] = []

    async def start(config: PlatformConfig, fleet_key: bytes | None) -> PlatformDaemon:
        daemon = PlatformDaemon(config, fleet_key)
        started.append(daemon)
        await daemon.start()
        return daemon

    yield start
    for daemon in started:
        await daemon.stop()
