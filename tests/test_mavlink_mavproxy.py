"""MAVProxy, a real ground station, against a --sim platform's MAVLink endpoint: it detects the
vehicle and names its mode, fetches the parameters (after MAVFTP's NAK), loads a
``QGC WPL 110`` mission and a fence, reads the mission back and starts the patrol with
``mode AUTO``. Commands are piped into its shell; its printed lines are what is checked."""

from __future__ import annotations

import asyncio
import contextlib
import json
import sys
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path

from conftest import free_udp_port, wait_until
from mavlink_gcs import LAT, LON, at, sim_rover_config

from brasidas import topics
from brasidas.messages import PatrolState, Velocity
from platformd.app import PlatformDaemon

MAVPROXY = Path(sys.executable).parent / "mavproxy.py"
"""Installed with the test extra (pyproject.toml)."""


class MavProxy:
    """mavproxy.py as a child process: commands on stdin, lines from stdout."""

    def __init__(self, process: asyncio.subprocess.Process) -> None:
        self.process = process
        self.lines: list[str] = []
        self._changed = asyncio.Event()

    async def read(self) -> None:
        assert self.process.stdout is not None
        while line := await self.process.stdout.readline():
            self.lines.append(line.decode(errors="replace").rstrip())
            self._changed.set()

    def send(self, command: str) -> int:
        """Type a command; returns where its output starts in :attr:`lines`."""
        assert self.process.stdin is not None
        mark = len(self.lines)
        self.process.stdin.write(command.encode() + b"\n")
        return mark

    async def expect(self, text: str, since: int = 0, timeout: float = 30.0) -> str:
        async def wait() -> str:
            while True:
                for line in self.lines[since:]:
                    if text in line:
                        return line
                self._changed.clear()
                await self._changed.wait()

        try:
            return await asyncio.wait_for(wait(), timeout)
        except TimeoutError:
            output = "\n".join(self.lines[since:])
            raise AssertionError(
                f"MAVProxy never printed {text!r}; it printed:\n{output}"
            ) from None


@contextlib.asynccontextmanager
async def mavproxy(port: int, cwd: Path) -> AsyncIterator[MavProxy]:
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        str(MAVPROXY),
        f"--master=udpin:127.0.0.1:{port}",
        "--no-state",
        stdin=asyncio.subprocess.PIPE,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.STDOUT,
        cwd=cwd,
    )
    client = MavProxy(process)
    reader = asyncio.create_task(client.read())
    try:
        yield client
    finally:
        if process.returncode is None:
            # MAVProxy's input thread outlives SIGTERM until its stdin ends.
            assert process.stdin is not None
            process.stdin.close()
            process.terminate()
            try:
                await asyncio.wait_for(process.wait(), 10)
            except TimeoutError:
                process.kill()
                await process.wait()
        await reader


def patrolling(daemon: PlatformDaemon) -> bool:
    status = daemon.bus.last(topics.PATROL_STATUS)
    return status is not None and status.state is PatrolState.PATROLLING


def write_waypoints(path: Path, rows: list[tuple[int, int, int, float, float, float]]) -> None:
    """A ``QGC WPL 110`` file: (current, frame, command, param1, lat, lon) per row."""
    lines = ["QGC WPL 110"]
    for index, (current, frame, command, param1, lat, lon) in enumerate(rows):
        fields = [index, current, frame, command, param1, 0, 0, 0, f"{lat:.8f}", f"{lon:.8f}", 0, 1]
        lines.append("\t".join(str(field) for field in fields))
    path.write_text("\n".join(lines) + "\n")


async def test_mavproxy_loads_a_mission_and_a_fence_and_starts_the_patrol(
    platform_factory: Callable[..., Awaitable[PlatformDaemon]], tmp_path: Path
) -> None:
    port = free_udp_port()
    daemon = await platform_factory(
        sim_rover_config(
            tmp_path,
            port,
            "mavlink.allow_unsigned_control=true",
            # MAVProxy prints a new mode from the heartbeat: sooner, not differently.
            "mavlink.heartbeat_hz=5",
        ),
        None,
    )
    patrol = daemon.ctx.patrol
    assert patrol is not None
    mission = tmp_path / "loop.waypoints"
    corners = [at(0, 0), at(40, 0), at(40, 30), at(0, 30), at(0, 0)]
    write_waypoints(
        mission,
        [(1, 0, 16, 0, LAT, LON)] + [(0, 3, 16, 0, lat, lon) for lat, lon in corners],
    )
    fence = tmp_path / "field.fence"
    boundary = [at(-12, -12), at(52, -12), at(52, 42), at(-12, 42)]
    write_waypoints(
        fence,
        [(0, 0, 5001, 4, lat, lon) for lat, lon in boundary] + [(0, 0, 5004, 6, *at(20, 15))],
    )

    async with mavproxy(port, tmp_path) as client:
        await client.expect("Detected vehicle 1:1")
        await client.expect("Mode HOLD")
        await client.expect("Received 1", timeout=60)  # every parameter, after FTP's NAK

        since = client.send(f"wp load {mission}")
        await client.expect("Sent all 6 waypoints", since)
        await client.expect("Got MISSION_ACK: TYPE_MISSION: ACCEPTED", since)
        assert patrol.core.route.closed
        assert patrol.core.route.stops == 4

        since = client.send("wp list")
        await client.expect("Requesting 6 waypoints", since)
        await client.expect(f"{corners[2][0]:.7f}", since)

        since = client.send(f"fence load {fence}")
        await client.expect("Got MISSION_ACK: TYPE_FENCE: ACCEPTED", since)
        area = patrol.core.area
        assert area is not None
        assert list(area.keepouts) == ["fence-1"]

        since = client.send("mode AUTO")
        await client.expect("Mode AUTO", since)
        assert patrolling(daemon)

        # "guided LAT LON": ArduPilot's guided waypoint, driven to through the planner.
        goal = at(30, 25)
        since = client.send(f"guided {goal[0]:.7f} {goal[1]:.7f} 0")
        await client.expect("Mode GUIDED", since)
        assert patrol.detour == "guided"
        (target,) = patrol.core.route.waypoints
        assert abs(target.latitude - goal[0]) < 1e-6
        assert abs(target.longitude - goal[1]) < 1e-6
        since = client.send("mode RTL")
        await client.expect("Mode RTL", since)
        assert patrol.detour == "home"

        # "rc 3 1750" in MANUAL: the throttle channel drives, as the joystick does.
        commands: list[Velocity] = []
        daemon.bus.subscribe(topics.MOTOR_COMMAND, commands.append)
        since = client.send("mode MANUAL")
        await client.expect("Mode MANUAL", since)
        client.send("rc 3 1750")
        await wait_until(lambda: any(c.linear > 0.3 for c in commands), 10)
        client.send("rc 3 1500")


async def test_mavproxy_controls_only_once_it_signs(
    platform_factory: Callable[..., Awaitable[PlatformDaemon]], tmp_path: Path
) -> None:
    port = free_udp_port()
    key_file = tmp_path / "mavlink.pass"
    key_file.write_text("brasidas-demo-passphrase\n")
    key_file.chmod(0o600)
    daemon = await platform_factory(
        sim_rover_config(tmp_path, port, f"mavlink.signing_key_file={key_file}"), None
    )
    async with mavproxy(port, tmp_path) as client:
        await client.expect("Mode HOLD")
        since = client.send("mode AUTO")
        await client.expect("refused: unsigned link", since)
        assert not patrolling(daemon)

        since = client.send("signing key brasidas-demo-passphrase")
        # AUTO arms through the pre-arm checks: as a pilot waits for the GPS lock first.
        arming = daemon.ctx.arming
        assert arming is not None
        await wait_until(lambda: arming.reasons() == (), 30)
        client.send("mode AUTO")
        await client.expect("Mode AUTO", since)
        assert patrolling(daemon)


async def test_mavproxy_fence_options_take_two_inclusion_fences_as_their_union(
    platform_factory: Callable[..., Awaitable[PlatformDaemon]], tmp_path: Path
) -> None:
    """Two overlapping inclusion fences: the area where both overlap (ArduPilot's default), then
    after ``param set FENCE_OPTIONS 2`` their union; a bit a rover cannot honour is refused;
    the value is kept across a restart (the next upload is still a union)."""
    fence = tmp_path / "two-fields.fence"
    # Both hold the demo route (0..40 m east, 0..30 m north) and the robot with room for its
    # GPS error (the simulated receiver's fix was seen 5.7 m west of the start: the overlap's
    # edge was 5 m away, and the upload refused); only one holds each far point.
    west = [at(-12, -12), at(45, -12), at(45, 42), at(-12, 42)]
    east = [at(-9, -12), at(52, -12), at(52, 42), at(-9, 42)]
    write_waypoints(fence, [(0, 0, 5001, 4, lat, lon) for lat, lon in west + east])
    far_east, far_west = at(48, 15), at(-11, 15)

    def allowed(daemon: PlatformDaemon, point: tuple[float, float]) -> bool:
        assert daemon.ctx.patrol is not None
        area = daemon.ctx.patrol.core.area
        assert area is not None
        return area.inside(*area.local(*point))

    port = free_udp_port()
    config = sim_rover_config(tmp_path, port, "mavlink.allow_unsigned_control=true")
    daemon = await platform_factory(config, None)
    async with mavproxy(port, tmp_path) as client:
        await client.expect("Detected vehicle 1:1")
        await client.expect("Received 1", timeout=60)

        since = client.send(f"fence load {fence}")
        await client.expect("Got MISSION_ACK: TYPE_FENCE: ACCEPTED", since)
        await client.expect("the boundary: the overlap of 2 inclusion polygons", since)
        assert not allowed(daemon, far_east)
        assert not allowed(daemon, far_west)

        since = client.send("param set FENCE_OPTIONS 2")
        await client.expect("several inclusion fences: their union", since)
        saved = tmp_path / "state" / "brasidas" / "mavlink-parameters.json"
        assert json.loads(saved.read_text()) == {"FENCE_OPTIONS": 2}

        since = client.send(f"fence load {fence}")
        await client.expect("Got MISSION_ACK: TYPE_FENCE: ACCEPTED", since)
        await client.expect("the boundary: the union of 2 inclusion polygons", since)
        assert allowed(daemon, far_east)
        assert allowed(daemon, far_west)

        since = client.send("param set FENCE_OPTIONS 3")
        await client.expect("FENCE_OPTIONS 3 refused: only bit 1", since)
        assert json.loads(saved.read_text()) == {"FENCE_OPTIONS": 2}
    await daemon.stop()

    port = free_udp_port()
    config = sim_rover_config(tmp_path, port, "mavlink.allow_unsigned_control=true")
    daemon = await platform_factory(config, None)
    async with mavproxy(port, tmp_path) as client:
        await client.expect("Detected vehicle 1:1")
        await client.expect("Received 1", timeout=60)
        since = client.send("param show FENCE_OPTIONS")
        shown = await client.expect("FENCE_OPTIONS", since)
        assert shown.split()[-1] == "2.0"
        # A wider eastern field than the map kept on disk has: only a union reaches it.
        wider = [at(-5, -12), at(70, -12), at(70, 42), at(-5, 42)]
        write_waypoints(fence, [(0, 0, 5001, 4, lat, lon) for lat, lon in west + wider])
        since = client.send(f"fence load {fence}")
        await client.expect("Got MISSION_ACK: TYPE_FENCE: ACCEPTED", since)
        assert allowed(daemon, at(65, 15))
        assert allowed(daemon, far_west)
