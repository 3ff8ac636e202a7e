"""Shared fixtures. Every test fails if it leaves tasks, timers or threads behind (STYLE.md §9)."""

from __future__ import annotations

import asyncio
import concurrent.futures.thread
import contextlib
import itertools
import logging
import os
import socket
import sys
import threading
import time
import types
from collections.abc import AsyncIterator, Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from gi.repository import GObject
from hypothesis import HealthCheck, settings
from support import markers
from support.browser import SharedChromium
from support.cli import run_cli as run_cli  # re-exported: modules import helpers from here

from brasidas.codecs.telemetry_schema import VelocityLink
from brasidas.config import PlatformConfig, StationConfig, load_config
from platformd.app import PlatformDaemon
from platformd.context import PlatformContext
from stationd.daemon import StationDaemon

pytest_plugins = ["pytester", "support.patrol"]  # support.patrol: the robot_factory fixture

# Property tests check what a codec does, not how fast: on a loaded 2-core machine (CI, or the
# browser tests running alongside) an example can exceed Hypothesis's 200 ms default deadline.
settings.register_profile("brasidas", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("brasidas")

# PyGObject turns GLib's own warnings (a bad cast, a handler id that is gone) into Python warnings
# of a class it names "gobject.Warning", a module that does not exist: pytest-xdist's controller
# could not rebuild one sent by a worker and stopped the whole run (INTERNALERROR). Named by the
# module it does live in, it reaches the warnings summary with the test that caused it.
GObject.Warning.__module__ = "gi._gi"


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist reads the groups
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    markers.apply(items)


def pytest_configure(config: pytest.Config) -> None:
    # A browser test's page assertions wait for what the page will show: Playwright's 5 s
    # default ran out once (load average ~18) while the page was merely slow, not wrong.
    with contextlib.suppress(ImportError):
        from playwright.async_api import expect

        expect.set_options(timeout=15_000)


@pytest.fixture(autouse=True)
def _isolated_state(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    """Keep fleet keys and other state out of the real home directory."""
    monkeypatch.setenv("XDG_STATE_HOME", str(tmp_path / "state"))
    yield


@pytest.fixture(autouse=True)
def _foxglove_on_ephemeral_ports(monkeypatch: pytest.MonkeyPatch) -> None:
    """Every station a test starts serves Foxglove on a port of the kernel's choice."""
    import stationd.foxglove_live

    monkeypatch.setattr(stationd.foxglove_live, "PORT_OVERRIDE", 0)


@pytest.fixture(autouse=True)
def _restore_logging() -> Iterator[None]:
    """A CLI's ``setup_logging`` replaces the root handlers with one bound to this test's
    captured stderr; left in place it would write to a closed file in every later test."""
    root = logging.getLogger()
    handlers, level = list(root.handlers), root.level
    yield
    root.handlers[:] = handlers
    root.setLevel(level)


THREAD_GRACE = 2.0
"""Seconds a test's threads get to finish after it (a pipeline's last state change)."""


def on_the_tests_loop(request: pytest.FixtureRequest, name: str) -> Any:
    """The fixture ``name`` in the variant for the loop this test runs on: ``name`` on its
    own loop, ``session_loop_<name>`` on the worker's session loop (the browser tests,
    :func:`support.markers.on_the_session_loop`). A fixture's loop is fixed where it is
    defined, so a fixture both kinds of test use is defined once for each."""
    if markers.on_the_session_loop(request.node):
        return request.getfixturevalue(f"session_loop_{name}")
    return request.getfixturevalue(f"own_loop_{name}")


@pytest.fixture(autouse=True)
def verify_no_lingering_tasks(request: pytest.FixtureRequest) -> None:
    """Fail a test that leaves tasks running, timers scheduled or threads working."""
    on_the_tests_loop(request, "verify_no_lingering_tasks")


@pytest.fixture
async def own_loop_verify_no_lingering_tasks() -> AsyncIterator[None]:
    async with no_lingering_tasks():
        yield


@pytest_asyncio.fixture(loop_scope="session")
async def session_loop_verify_no_lingering_tasks(playwright_driver: Any) -> AsyncIterator[None]:
    # The driver's own tasks (started by the worker's first browser test) are not the
    # test's. The test body runs on the loop current when it starts: this one.
    asyncio.set_event_loop(asyncio.get_running_loop())
    async with no_lingering_tasks():
        yield


@contextlib.asynccontextmanager
async def no_lingering_tasks() -> AsyncIterator[None]:
    """Fail if the block leaves tasks running, timers scheduled or threads working."""
    loop = asyncio.get_running_loop()
    tasks_before = asyncio.all_tasks()
    timers_before = set(_timers(loop))
    threads_before = set(threading.enumerate())
    yield
    # Give cancelled tasks one turn of the loop to finish unwinding.
    await asyncio.sleep(0)
    lingering = [
        task
        for task in asyncio.all_tasks() - tasks_before
        if not task.done() and task is not asyncio.current_task()
    ]
    for task in lingering:
        task.cancel()
    assert not lingering, f"test left tasks running: {[t.get_name() for t in lingering]}"

    timers = [timer for timer in _timers(loop) if timer not in timers_before]
    described = [repr(timer) for timer in timers]
    for timer in timers:
        timer.cancel()
    assert not timers, f"test left timers scheduled: {described}"

    deadline = time.monotonic() + THREAD_GRACE
    while threads := _working_threads(threads_before):
        if time.monotonic() > deadline:
            break
        await asyncio.sleep(0.02)
    assert not threads, f"test left threads working: {[t.name for t in threads]}"


def _timers(loop: asyncio.AbstractEventLoop) -> list[asyncio.TimerHandle]:
    """The loop's ``call_later``/``call_at`` handles still due (the asyncio event loop's
    private list: there is no public one)."""
    scheduled: list[asyncio.TimerHandle] = getattr(loop, "_scheduled", [])
    return [timer for timer in scheduled if not timer.cancelled()]


def _working_threads(before: set[threading.Thread]) -> list[threading.Thread]:
    """Threads started since ``before`` that are still alive and not an idle pool worker."""
    frames = sys._current_frames()
    return [
        thread
        for thread in threading.enumerate()
        if thread not in before
        and thread.is_alive()
        and not _idle_pool_worker(frames.get(thread.ident or -1))
    ]


def _idle_pool_worker(frame: types.FrameType | None) -> bool:
    """A ``concurrent.futures`` worker waiting for work (an executor that is not shut down
    yet, like the loop's default one until the loop closes); a busy one runs a work item."""
    return (
        frame is not None
        and frame.f_code.co_name == "_worker"
        and frame.f_code.co_filename == concurrent.futures.thread.__file__
    )


async def wait_until(predicate: Callable[[], bool], timeout: float = 5.0) -> None:
    """Poll ``predicate`` until true; fails the test after a generous ``timeout``."""

    async def poll() -> None:
        while not predicate():
            await asyncio.sleep(0.01)

    await asyncio.wait_for(poll(), timeout)


async def until_armable(ctx: PlatformContext, timeout: float = 20.0) -> None:
    """Wait until the platform's pre-arm checks pass (GPS fix, controller answering): what a
    pilot waits for before a start, which arms through them (platformd.arming)."""
    arming = ctx.arming
    assert arming is not None
    await wait_until(lambda: not arming.reasons(), timeout)


def hang_serial_opens(monkeypatch: pytest.MonkeyPatch) -> tuple[threading.Event, list[float]]:
    """Every serial open blocks (as in a USB adapter's hung driver) until the returned event
    is set (at most 3 s: code that blocks the loop on it must fail, not hang); the list
    records when each open began."""
    import serial

    release = threading.Event()
    calls: list[float] = []
    real_open = serial.Serial.open

    def hung_open(self: serial.Serial) -> None:
        calls.append(time.monotonic())
        release.wait(3.0)
        real_open(self)

    monkeypatch.setattr(serial.Serial, "open", hung_open)
    return release, calls


async def record_loop_gaps(gaps: list[float]) -> None:
    """Until cancelled: the time between turns of a 10 ms sleep (a stalled loop shows)."""
    last = time.monotonic()
    while True:
        await asyncio.sleep(0.01)
        now = time.monotonic()
        gaps.append(now - last)
        last = now


def udp_port_bound(port: int) -> bool:
    """A socket on this host (any process) is bound to UDP ``port`` (``/proc/net/udp[6]``)."""
    for table in ("/proc/net/udp", "/proc/net/udp6"):
        with contextlib.suppress(FileNotFoundError), open(table) as lines:
            next(lines)  # the header
            for line in lines:
                local = line.split()[1]  # "0100007F:1F90": address and port in hex
                if int(local.rpartition(":")[2], 16) == port:
                    return True
    return False


PORTS_FROM = 22000
"""Ports handed to the daemons a test starts come from below the kernel's ephemeral range
(32768 and up): a port found free by binding port 0 and closing was the kernel's to give to
the next client socket or another worker's probe, and now and then a daemon's bind lost it
("Address already in use"). Each xdist worker has a block of its own."""
PORTS_PER_WORKER = 1250
_next_port = itertools.count()


def _free_port(kind: int) -> int:
    worker = os.environ.get("PYTEST_XDIST_WORKER", "gw0").removeprefix("gw")
    first = PORTS_FROM + (int(worker) % 8 if worker.isdigit() else 0) * PORTS_PER_WORKER
    for _ in range(PORTS_PER_WORKER):
        port = first + next(_next_port) % PORTS_PER_WORKER
        with socket.socket(socket.AF_INET, kind) as sock:
            try:
                sock.bind(("0.0.0.0", port))
            except OSError:
                continue  # taken (a daemon of this worker's, or a TCP port in TIME_WAIT)
            return port
    raise RuntimeError(f"no free port in {first}..{first + PORTS_PER_WORKER - 1}")


def free_udp_port() -> int:
    return _free_port(socket.SOCK_DGRAM)


def free_tcp_port() -> int:
    return _free_port(socket.SOCK_STREAM)


@pytest.fixture(scope="session")
def chromium(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SharedChromium]:
    """The worker's one headless Chromium (tests/support/browser.py), started when first used."""
    running = SharedChromium(tmp_path_factory.mktemp("chromium"))
    yield running
    running.close()


@pytest_asyncio.fixture(scope="session", loop_scope="session")
async def playwright_driver() -> AsyncIterator[Any]:
    """The worker's one Playwright driver (a Node process, 0.5-1.2 s to start), on the
    session loop the browser tests run on: a driver is bound to the loop that started it."""
    from playwright.async_api import async_playwright

    async with async_playwright() as playwright:
        yield playwright


@pytest_asyncio.fixture(loop_scope="session")
async def browser(chromium: SharedChromium, playwright_driver: Any) -> AsyncIterator[Any]:
    """The worker's Chromium, connected for this test: each ``new_page`` or ``new_context``
    is a fresh context (no cookies or storage from another test), all closed after it."""
    connected = await playwright_driver.chromium.connect_over_cdp(chromium.endpoint())
    try:
        yield connected
    finally:
        await connected.close()


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
        "recorder.enabled=false",  # tests of the recorder switch it on (tests/test_recorder.py)
        # No latency assumed without a report: the speed cap stays out of the way of tests that
        # are not about it (tests/test_speedcap.py sets the default worst case back).
        "safety.worst_latency_ms=0",
    ]
    return load_config(PlatformConfig, None, [*defaults, *overrides])


PlatformFactory = Callable[..., Awaitable[PlatformDaemon]]


@pytest.fixture
def platform_factory(request: pytest.FixtureRequest) -> PlatformFactory:
    """Start in-process platforms; all are stopped after the test."""
    factory: PlatformFactory = on_the_tests_loop(request, "platform_factory")
    return factory


@pytest.fixture
async def own_loop_platform_factory() -> AsyncIterator[PlatformFactory]:
    async with platforms_started() as start:
        yield start


@pytest_asyncio.fixture(loop_scope="session")
async def session_loop_platform_factory() -> AsyncIterator[PlatformFactory]:
    async with platforms_started() as start:
        yield start


@contextlib.asynccontextmanager
async def platforms_started() -> AsyncIterator[PlatformFactory]:
    """A function that starts an in-process platform; every one it started is stopped on exit."""
    started: list[PlatformDaemon] = []

    async def start(config: PlatformConfig, fleet_key: bytes | None) -> PlatformDaemon:
        daemon = PlatformDaemon(config, fleet_key)
        started.append(daemon)
        await daemon.start()
        return daemon

    try:
        yield start
    finally:
        for daemon in started:
            await daemon.stop()


def velocities_dropped(daemon: PlatformDaemon, reason: str) -> int:
    """The platform's velocity receiver's drop counter for ``reason``, as telemetry reads it
    (now, not at the next telemetry push)."""
    link = daemon.ctx.telemetry.build_one(VelocityLink)
    return link.dropped.get(reason, 0) if isinstance(link, VelocityLink) else 0


def velocities_accepted(daemon: PlatformDaemon) -> int:
    """The velocity packets the platform's receiver has accepted (now, as telemetry reads it)."""
    link = daemon.ctx.telemetry.build_one(VelocityLink)
    return link.accepted if isinstance(link, VelocityLink) else 0


@contextlib.asynccontextmanager
async def running_station(key: bytes, *overrides: str) -> AsyncIterator[StationDaemon]:
    """A station daemon on loopback with an ephemeral API port; stopped on exit."""
    config = load_config(
        StationConfig,
        None,
        [
            "station.api_port=0",
            f"discovery.port={free_udp_port()}",
            "discovery.bind_host=127.0.0.1",
            *overrides,
        ],
    )
    daemon = StationDaemon(config, key)
    await daemon.start()
    try:
        yield daemon
    finally:
        await daemon.stop()


@pytest.fixture
def station_settings() -> tuple[str, ...]:
    """The ``station`` fixture's settings: a module overrides this fixture, a test
    parametrizes it."""
    return ()


@pytest.fixture
def station(
    request: pytest.FixtureRequest, fleet_key: bytes, station_settings: tuple[str, ...]
) -> StationDaemon:
    """A station on loopback (:func:`running_station`) with ``station_settings``."""
    daemon: StationDaemon = on_the_tests_loop(request, "station")
    return daemon


@pytest.fixture
async def own_loop_station(
    fleet_key: bytes, station_settings: tuple[str, ...]
) -> AsyncIterator[StationDaemon]:
    async with running_station(fleet_key, *station_settings) as daemon:
        yield daemon


@pytest_asyncio.fixture(loop_scope="session")
async def session_loop_station(
    fleet_key: bytes, station_settings: tuple[str, ...]
) -> AsyncIterator[StationDaemon]:
    async with running_station(fleet_key, *station_settings) as daemon:
        yield daemon
