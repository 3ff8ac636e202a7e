"""Arming, pre-arm checks, the stop for everyone and the operator's last word (issue 27)."""

from __future__ import annotations

import asyncio
import json
import signal
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from conftest import free_tcp_port, wait_until
from support.processes import sim_platform

from brasidas import security, topics
from brasidas.bus import Bus
from brasidas.codecs.jsonrpc import RpcError
from brasidas.messages import ArmingState, ControllerStatus, ImuStatus, OverrideState, Velocity
from platformd.arbiter import MotionArbiter
from platformd.arming import CLOCK_SET_AFTER, PrearmInputs, prearm_reasons
from platformd.sim.demo_area import demo_map
from stationd.client import PlatformConnection

NOW = CLOCK_SET_AFTER + 1000.0


# --------------------------------------------------------------------------- pre-arm checks


def test_prearm_names_every_failing_check_and_passes_when_healthy() -> None:
    bad = PrearmInputs(
        now=100.0,
        wall=0.0,
        gps_enabled=True,
        fix_age_s=None,
        imu_enabled=True,
        imu_age_s=None,
        up_s=10.0,
        motor_enabled=True,
        controller=ControllerStatus(False, error="no answer on /dev/ttyUSB0"),
        recorder_error="disk full",
        map_error="self-intersection",
    )
    assert prearm_reasons(bad) == (
        "PreArm: no GPS fix",
        "PreArm: IMU silent",
        "PreArm: motor controller not answering (no answer on /dev/ttyUSB0)",
        "PreArm: map refused: self-intersection",
        "PreArm: recorder cannot write: disk full",
        "PreArm: clock not set",
    )
    # Engaging the override (driving by hand) needs none of them.
    assert prearm_reasons(bad, manual=True) == ()
    good = PrearmInputs(
        now=100.0,
        wall=NOW,
        gps_enabled=True,
        fix_age_s=0.2,
        imu_enabled=True,
        imu=ImuStatus(True),
        imu_age_s=0.5,
        motor_enabled=True,
        controller=ControllerStatus(True),
    )
    assert prearm_reasons(good) == ()
    stale = PrearmInputs(now=100.0, wall=NOW, gps_enabled=True, fix_age_s=2.5, fix_stale_s=2.0)
    assert prearm_reasons(stale) == ("PreArm: no GPS fix",)
    failed_imu = PrearmInputs(
        now=1.0, wall=NOW, imu_enabled=True, imu=ImuStatus(False, "WHO_AM_I 0x00"), imu_age_s=0.1
    )
    assert prearm_reasons(failed_imu) == ("PreArm: IMU: WHO_AM_I 0x00",)
    starting = PrearmInputs(now=1.0, wall=NOW, imu_enabled=True, imu=ImuStatus(False), up_s=1.0)
    assert prearm_reasons(starting) == ()  # no sample yet, no error: starting, not silent
    silent = PrearmInputs(now=9.0, wall=NOW, imu_enabled=True, imu_age_s=4.0, up_s=9.0)
    assert prearm_reasons(silent) == ("PreArm: IMU silent",)


# --------------------------------------------------------------------------- the arbiter's gate


class _Timer:
    def cancel(self) -> None:
        pass


def test_disarmed_nothing_but_zero_reaches_the_motors() -> None:
    bus = Bus()
    now = [0.0]
    arbiter = MotionArbiter(
        bus, deadman=0.3, clock=lambda: now[0], call_later=lambda delay, callback: _Timer()
    )
    commands: list[Velocity] = []
    bus.subscribe(topics.MOTOR_COMMAND, commands.append)
    arbiter.start()
    bus.publish(topics.CMD_VEL, Velocity(0.5, 0.1))
    assert commands[-1] == Velocity(0.5, 0.1)  # armed (no arming actor): as before

    bus.publish(topics.ARMING_STATE, ArmingState(False, "stop by observer"))
    assert commands[-1] == Velocity(0.0, 0.0)
    commands.clear()
    bus.publish(topics.CMD_VEL, Velocity(0.5, 0.1))
    bus.publish(topics.OVERRIDE_STATE, OverrideState(True, "s1", "alpha"))
    bus.publish(topics.TELEOP_VELOCITY, Velocity(1.0, 0.0))
    bus.publish(topics.OVERRIDE_STATE, OverrideState(False))
    bus.publish(topics.CMD_VEL, Velocity(0.3, 0.0))
    assert commands
    assert all(c == Velocity(0.0, 0.0) for c in commands)

    bus.publish(topics.ARMING_STATE, ArmingState(True, "armed by alpha"))
    bus.publish(topics.CMD_VEL, Velocity(0.3, 0.0))
    assert commands[-1] == Velocity(0.3, 0.0)


# --------------------------------------------------------------------------- a real process


class Platform:
    """``python -m platformd --sim`` on files in ``tmp_path``; killed with SIGKILL."""

    def __init__(self, tmp_path: Path) -> None:
        self.tmp_path = tmp_path
        self.port = free_tcp_port()
        self.process: asyncio.subprocess.Process | None = None
        self.log = tmp_path / "platform.log"

    async def start(self) -> None:
        settings = [
            "sim.demo_map=false",
            f"map.file={self.tmp_path / 'map.geojson'}",
            f"autonomy.route_file={self.tmp_path / 'route.json'}",
            f"arming.state_file={self.tmp_path / 'last_word.json'}",
            "arming.countdown_s=1",
            f"recorder.dir={self.tmp_path / 'recordings'}",
        ]
        with self.log.open("ab") as log:
            self.process, _port = await sim_platform(*settings, port=self.port, stderr=log)

    async def connect(self, station_id: str) -> PlatformConnection:
        async def attempt() -> PlatformConnection:
            while True:
                assert self.process is not None
                assert self.process.returncode is None
                if not security.default_key_path().exists():  # --sim makes it at start
                    await asyncio.sleep(0.1)
                    continue
                connection = PlatformConnection(
                    "brasidas-1",
                    f"http://127.0.0.1:{self.port}",
                    station_id=station_id,
                    fleet_key=security.load_key(security.default_key_path()),
                )
                try:
                    await connection.open()
                    return connection
                except OSError:
                    await connection.close()
                    await asyncio.sleep(0.1)

        return await asyncio.wait_for(attempt(), 20)

    async def kill(self) -> None:
        if self.process is not None and self.process.returncode is None:
            self.process.send_signal(signal.SIGKILL)
            await self.process.wait()


@pytest.fixture
async def platform(tmp_path: Path) -> AsyncIterator[Platform]:
    running = Platform(tmp_path)
    try:
        yield running
    finally:
        await running.kill()


async def _poll(connection: PlatformConnection, method: str, check: Any, timeout: float) -> Any:
    """Call ``method`` until ``check(answer)``; the last answer."""
    answer: Any = None

    async def loop() -> None:
        nonlocal answer
        while True:
            answer = await connection.call(method)
            if check(answer):
                return
            await asyncio.sleep(0.1)

    try:
        await asyncio.wait_for(loop(), timeout)
    except TimeoutError:
        raise AssertionError(f"{method}: {answer}") from None
    return answer


async def test_kill_9_after_a_stop_stays_stopped_and_after_a_start_resumes_through_countdown(
    platform: Platform,
) -> None:
    await platform.start()
    operator = await platform.connect("alpha")
    observer = await platform.connect("observer")
    try:
        await operator.call("load_map", map=demo_map(37.9415, 23.6530))
        await operator.call("set_waypoints", waypoints=["sw", "se", "ne", "sw"])
        # A start arms through the checks (a fix, the IMU, the controller: wait for them).
        await _poll(operator, "get_arming", lambda a: a["ready"], 20)
        assert (await operator.call("patrol_start"))["state"] in ("patrolling", "holding")
        assert (await operator.call("get_arming"))["armed"] is True
        # An observer cannot arm, but may stop: motors to zero, the patrol stopped, on disk.
        with pytest.raises(RpcError, match="refused: control held by station alpha"):
            await observer.call("arm")
        answer = await observer.call("stop")
        assert answer["armed"] is False
        assert answer["last_stop"].startswith("stop by observer")
        word = json.loads((platform.tmp_path / "last_word.json").read_text())
        assert word["word"] == "stop"
        assert word["by"] == "observer"
        assert (await operator.call("get_patrol"))["state"] == "stopped"
    finally:
        await operator.close()
        await observer.close()

    await platform.kill()  # no clean shutdown
    await platform.start()
    watcher = await platform.connect("watcher")
    try:
        # Every check passes (autostart would count down now): still stopped, disarmed.
        await _poll(watcher, "get_arming", lambda a: a["ready"], 20)
        await asyncio.sleep(0)
        arming = await watcher.call("get_arming")
        assert arming["armed"] is False
        assert arming["countdown_s"] is None
        assert arming["last_stop"].startswith("stop by observer")
        assert (await watcher.call("get_patrol"))["state"] != "patrolling"
        # The operator starts it again: that is the new last word.
        assert (await watcher.call("patrol_start"))["state"] in ("patrolling", "holding")
        await _poll(
            watcher,
            "get_arming",
            lambda a: (
                json.loads((platform.tmp_path / "last_word.json").read_text())["word"] == "start"
            ),
            5,
        )
    finally:
        await watcher.close()

    await platform.kill()
    await platform.start()
    watcher = await platform.connect("watcher")
    try:
        # After a start, autostart resumes it: announced, then armed and patrolling.
        await _poll(watcher, "get_patrol", lambda p: p["state"] == "patrolling", 30)
        assert (await watcher.call("get_arming"))["armed"] is True
        # A patrol stop is answered once it is on disk (a kill -9 right after keeps it).
        await watcher.call("patrol_stop")
        word = json.loads((platform.tmp_path / "last_word.json").read_text())
        assert word["word"] == "stop"
    finally:
        await watcher.close()
    log = platform.log.read_text()
    assert "autostart: arming and patrolling in 1 s" in log
    assert "not resuming the patrol: the last word was stop by observer" in log


# --------------------------------------------------------------------------- ground stations

PASSPHRASE = "correct horse battery staple"


async def test_a_signed_non_controlling_ground_station_stops_and_an_unsigned_one_cannot(
    platform_factory: Any, tmp_path: Path
) -> None:
    from mavlink_gcs import Gcs, sim_rover_config
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    key_file = tmp_path / "mavlink.pass"
    key_file.write_text(PASSPHRASE + "\n")
    key_file.chmod(0o600)
    holder, other, stranger = [await Gcs.open(system) for system in (255, 254, 253)]
    try:
        daemon = await platform_factory(
            sim_rover_config(
                tmp_path, holder.port, "gps.sim_rate_hz=10", f"mavlink.signing_key_file={key_file}"
            ),
            None,
        )
        heartbeat = await holder.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 1)
        assert not heartbeat.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED  # disarmed at start
        for gcs in (holder, other, stranger):
            gcs.vehicle = holder.vehicle
        holder.sign(PASSPHRASE)
        other.sign(PASSPHRASE)
        arming = daemon.ctx.arming
        assert arming is not None
        await wait_until(lambda: not arming.reasons(), 20)
        # SYS_STATUS's pre-arm bit says arming would pass (MAVSDK's is_armable).
        await holder.expect(
            "SYS_STATUS",
            lambda m: m.onboard_control_sensors_health & mavlink.MAV_SYS_STATUS_PREARM_CHECK,
        )
        ack = await holder.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED
        ack = await holder.command(mavlink.MAV_CMD_MISSION_START)
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED
        await holder.expect(
            "HEARTBEAT",
            lambda m: (
                m.get_srcComponent() == 1
                and m.custom_mode == 10
                and m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
            ),
        )

        # Unsigned: no stop, no disarm; the robot patrols on.
        ack = await stranger.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196)
        assert ack.result == mavlink.MAV_RESULT_DENIED
        assert arming.armed

        # Signed, not holding control: arming is refused, HOLD and force-disarm are not.
        ack = await other.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        assert ack.result in (mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED)
        ack = await other.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 4)  # HOLD
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED
        assert not arming.armed
        motion = daemon.bus.last(topics.MOTION_STATE)
        assert motion is not None
        assert motion.command == Velocity(0.0, 0.0)
        status = daemon.bus.last(topics.PATROL_STATUS)
        assert status is not None
        assert status.state.value == "stopped"
        assert arming.last_word is not None
        assert arming.last_word.word == "hold"
        assert arming.last_word.by == f"gcs254@127.0.0.1:{other.port}"
        await holder.expect(
            "HEARTBEAT",
            lambda m: (
                m.get_srcComponent() == 1 and not m.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
            ),
        )
        # Re-arming needs control: the other ground station is refused with the holder's id.
        ack = await other.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        assert ack.result == mavlink.MAV_RESULT_DENIED
        assert ack.result_param2 == 255
        ack = await holder.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1)
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED
        assert arming.armed
        since = holder.mark()
        ack = await other.command(mavlink.MAV_CMD_DO_FLIGHTTERMINATION, 1)
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED
        assert not arming.armed
        await holder.expect_text(lambda t: "terminate (forced) by gcs254" in t, since)
        ack = await holder.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196)
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED
        assert arming.last_word.word == "disarm"
    finally:
        for gcs in (holder, other, stranger):
            gcs.close()


# --------------------------------------------------------------------------- the CLI


async def test_cli_stop_arm_and_disarm(
    station: Any, platform_factory: Any, fleet_key: bytes, tmp_path: Path
) -> None:
    from conftest import quiet_platform_config
    from support.cli import run_cli

    platform = await platform_factory(
        quiet_platform_config(
            "platform.id=rover-7",
            "motor.enabled=true",
            f"motor.port={tmp_path / 'no-such-port'}",
            f"arming.state_file={tmp_path / 'last_word.json'}",
        ),
        fleet_key,
    )
    code, _, _ = await run_cli(station, "connect", "rover-7", "--url", platform.ctx.signaling_url)
    assert code == 0
    code, out, err = await run_cli(station, "arm", "rover-7")
    assert code != 0
    assert "PreArm: motor controller not answering" in err
    code, out, _ = await run_cli(station, "stop", "rover-7")
    station_id = station.ctx.config.station.id
    assert code == 0
    assert "disarmed" in out
    assert f"last stop: stop by {station_id}" in out
    code, out, _ = await run_cli(station, "status", "rover-7")
    (line,) = [line for line in out.splitlines() if line.startswith("arming")]
    assert "disarmed" in line
    assert "PreArm: motor controller not answering" in line
    code, out, _ = await run_cli(station, "disarm", "rover-7", "--force", "--json")
    assert code == 0
    assert json.loads(out)["armed"] is False
    word = json.loads((tmp_path / "last_word.json").read_text())
    assert word == {"word": "disarm", "by": station_id, "at": word["at"]}


async def test_gcs_loss_in_auto_holds_when_configured(
    platform_factory: Any, tmp_path: Path
) -> None:
    from mavlink_gcs import Gcs, sim_rover_config
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    gcs = await Gcs.open()
    try:
        daemon = await platform_factory(
            sim_rover_config(
                tmp_path,
                gcs.port,
                "mavlink.allow_unsigned_control=true",
                "failsafe.gcs_loss_action=hold",
                "signaling.session_timeout=2",
            ),
            None,
        )
        await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 1)
        arming = daemon.ctx.arming
        assert arming is not None
        await wait_until(lambda: not arming.reasons(), 20)
        ack = await gcs.command(mavlink.MAV_CMD_MISSION_START)
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED
        status = daemon.bus.last(topics.PATROL_STATUS)
        assert status is not None
        assert status.state.value in ("patrolling", "holding")
        # The ground station falls silent: its session times out, the patrol holds.
        await wait_until(
            lambda: (
                (s := daemon.bus.last(topics.PATROL_STATUS)) is not None
                and s.state.value == "stopped"
            ),
            10,
        )
        assert arming.last_word is not None
        assert arming.last_word.word == "hold"
        assert arming.last_word.by == f"gcs255@127.0.0.1:{gcs.port} lost"
    finally:
        gcs.close()


async def test_the_heartbeat_is_critical_while_the_ladder_holds_and_not_after_it_released(
    platform_factory: Any, tmp_path: Path
) -> None:
    """Before: CRITICAL stayed for as long as the released state did (60 s+ of patrolling)."""
    from mavlink_gcs import Gcs, sim_rover_config
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from brasidas.messages import FailsafeStep

    gcs = await Gcs.open()
    try:
        daemon = await platform_factory(
            sim_rover_config(
                tmp_path,
                gcs.port,
                "mavlink.allow_unsigned_control=true",
                "failsafe.release_after=3",
            ),
            None,
        )
        await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 1)
        ack = await gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 0)  # MANUAL, then silence
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED
        await gcs.expect(
            "HEARTBEAT",
            lambda m: m.get_srcComponent() == 1 and m.system_status == mavlink.MAV_STATE_CRITICAL,
            timeout=10,
        )
        await wait_until(
            lambda: (
                (f := daemon.bus.last(topics.FAILSAFE_STATE)) is not None
                and f.step is FailsafeStep.RELEASED
            ),
            10,
        )
        await gcs.expect(
            "HEARTBEAT",
            lambda m: m.get_srcComponent() == 1 and m.system_status == mavlink.MAV_STATE_ACTIVE,
            timeout=5,
        )
    finally:
        gcs.close()
