"""Every onboard automation can be switched off live (R-3): commands 10.8-10.10, 20.0, 20.4."""

from __future__ import annotations

from pathlib import Path

from conftest import quiet_platform_config, wait_until

from brasidas import topics
from brasidas.codecs.commands import (
    AUTO_FRAMERATE,
    BATTERY_MONITOR,
    DIAGNOSTICS,
    PATROL,
    STREAM_RETRIES,
    CommandCode,
)
from brasidas.codecs.jsonrpc import RpcError
from brasidas.codecs.telemetry_schema import Automation
from brasidas.messages import CommandResult, OverrideState
from platformd.app import PlatformDaemon
from platformd.media import MediaService


async def test_each_automation_switches_off_and_on_with_its_state_in_telemetry(
    tmp_path: Path,
) -> None:
    config = quiet_platform_config(
        "sim.enabled=true",
        "motor.enabled=true",
        "gps.enabled=true",
        "navcam.enabled=true",
        f"map.file={tmp_path / 'map.geojson'}",
        f"autonomy.route_file={tmp_path / 'route.json'}",
    )
    daemon = PlatformDaemon(config, None)
    await daemon.start()
    try:
        ctx = daemon.ctx

        async def send(code: CommandCode, payload: str) -> CommandResult:
            return await ctx.commands.dispatch(code, payload, None)

        def switches() -> dict[str, bool]:
            section = ctx.telemetry.build_one(Automation)
            assert isinstance(section, Automation)
            return section.switches

        expected = {
            "patrol": True,
            "auto_framerate": True,
            "stream_retries": True,
            "battery_monitor": True,
            "diagnostics": False,
        }
        await wait_until(lambda: switches() == expected)

        # 10.8: the patrol off stops it and refuses a start; on again, it starts.
        arming = ctx.arming  # a start arms through the pre-arm checks (issue 27)
        assert arming is not None
        await wait_until(lambda: not arming.reasons(), 20)
        await ctx.rpc.call_local("patrol_start")  # the --sim demo map and loop
        assert (await send(PATROL, "False")).accepted
        patrol = ctx.bus.last(topics.PATROL_STATUS)
        assert patrol is not None
        assert patrol.state == "stopped"
        assert not patrol.enabled
        assert patrol.reason == "patrol switched off"
        try:
            await ctx.rpc.call_local("patrol_start")
            raise AssertionError("started while switched off")
        except RpcError as err:
            assert "switched off" in err.message
        assert (await send(PATROL, "True")).accepted
        await ctx.rpc.call_local("patrol_start")
        assert ctx.bus.last(topics.PATROL_STATUS).enabled  # type: ignore[union-attr]

        # 10.9: with the automatic switch off the NavCam keeps its rate under the override.
        media = next(a for a in daemon.supervisor.actors if isinstance(a, MediaService))
        assert media.navcam is not None
        assert media.navcam.settings.framerate == 5
        assert (await send(AUTO_FRAMERATE, "off")).accepted
        ctx.bus.publish(topics.OVERRIDE_STATE, OverrideState(True, "s", "station"))
        assert media.navcam.settings.framerate == 5
        answer = await send(AUTO_FRAMERATE, "on")
        assert answer.accepted
        assert answer.result == {"auto_framerate": True, "navcam_fps": 30}
        assert media.navcam.settings.framerate == 30
        ctx.bus.publish(topics.OVERRIDE_STATE, OverrideState(False))
        assert media.navcam.settings.framerate == 5

        # 10.10, 20.0, 20.4
        assert (await send(STREAM_RETRIES, "False")).accepted
        assert all(not stream.retry for stream in media.streams.values())
        assert (await send(DIAGNOSTICS, "True")).accepted
        assert (await send(BATTERY_MONITOR, "False")).accepted
        await wait_until(
            lambda: (
                switches()
                == expected
                | {"stream_retries": False, "diagnostics": True, "battery_monitor": False}
            )
        )
        assert not (await send(PATROL, "maybe")).accepted
    finally:
        await daemon.stop()
