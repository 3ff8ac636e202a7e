"""Issue 26, defect 1 on the real UDP endpoint: a listener records a signed ground station
driving (MANUAL, the joystick, HOLD); the recording, sent from another source port, and again
after the platform restarts, commands nothing."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

from conftest import wait_until
from mavlink_gcs import Gcs, sim_rover_config
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas import topics
from brasidas.messages import Velocity
from platformd.app import PlatformDaemon

PASSPHRASE = "correct horse battery staple"


async def replay(daemon: PlatformDaemon, capture: list[bytes], motors: list[Velocity]) -> Gcs:
    """Send ``capture`` from a new source port; wait until every frame was judged."""
    counters = daemon.ctx.telemetry.counters["mavlink"]
    replayed = counters().get("replayed", 0)
    attacker = await Gcs.open(system=255)
    attacker.vehicle = ("127.0.0.1", daemon.ctx.mavlink_port)
    for frame in capture:
        attacker.send_raw(frame)
        await asyncio.sleep(0.05)
    await wait_until(lambda: counters().get("replayed", 0) >= replayed + len(capture))
    return attacker


async def test_a_recorded_signed_session_replayed_later_and_after_a_restart_drives_nothing(
    platform_factory: Any, tmp_path: Path
) -> None:
    key_file = tmp_path / "mavlink.pass"
    key_file.write_text(PASSPHRASE + "\n")
    key_file.chmod(0o600)
    gcs = await Gcs.open()
    try:
        config = sim_rover_config(tmp_path, gcs.port, f"mavlink.signing_key_file={key_file}")
        daemon = await platform_factory(config, None)
        await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 1)
        gcs.sign(PASSPHRASE)
        gcs.send(
            mavlink.MAVLink_heartbeat_message(
                mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3
            )
        )
        motors: list[Velocity] = []
        daemon.bus.subscribe(topics.MOTOR_COMMAND, motors.append)
        ack = await gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 0)
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED
        for _ in range(5):
            gcs.send(mavlink.MAVLink_manual_control_message(1, 500, 0, 500, 0, 0))
            await asyncio.sleep(0.05)
        await wait_until(lambda: any(c.linear > 0 for c in motors))
        ack = await gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 4)
        assert ack.result == mavlink.MAV_RESULT_ACCEPTED
        capture = list(gcs.frames)  # what a listener on the mesh recorded
        gcs.close()
        await wait_until(lambda: motors[-1].linear == 0)

        moved = len(motors)
        attacker = await replay(daemon, capture, motors)
        claimed = f"127.0.0.1:{attacker.port}"
        attacker.close()
        assert not [m for m in attacker.received if m.get_type() == "COMMAND_ACK"]
        assert not any(c.linear for c in motors[moved:])
        controller = daemon.ctx.authority.controller
        assert controller is None or claimed not in controller.station_id

        # A restart: the saved replay table refuses the same recording.
        await daemon.stop()
        restarted = await platform_factory(config, None)
        motors_after: list[Velocity] = []
        restarted.bus.subscribe(topics.MOTOR_COMMAND, motors_after.append)
        attacker = await replay(restarted, capture, motors_after)
        attacker.close()
        assert not [m for m in attacker.received if m.get_type() == "COMMAND_ACK"]
        assert not any(c.linear for c in motors_after)
        assert restarted.ctx.authority.controller is None
    finally:
        gcs.close()
