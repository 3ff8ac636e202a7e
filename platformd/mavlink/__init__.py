"""The MAVLink 2 endpoint (issue 22): the platform as a ground rover for QGroundControl,
Mission Planner, MAVProxy and MAVSDK. ``[mavlink] enabled`` turns it on.

``vehicle`` is the sans-IO protocol (pymavlink for the wire format), composed of ``link`` (the
links, admission, signing, sending), ``telemetry`` (the encoders), ``commands`` (commands,
modes, the joystick, parameters) and ``mission_protocol`` (transfers); ``missions`` the mission
and fence items' wire form (their meaning is brasidas.mapfiles.mission's), ``modes`` the identity and modes, ``signing`` the key and the signature
check, ``service`` the UDP transport and the platform's decisions.
"""

from __future__ import annotations

from pathlib import Path

from brasidas.config import PlatformConfig
from platformd.context import PlatformContext
from platformd.mavlink.signing import load_signing_key


def preload(config: PlatformConfig) -> None:
    """The service with pymavlink when ``mavlink.enabled``; with a lidar, its proximity sender."""
    if not config.mavlink.enabled:
        return
    import platformd.mavlink.service

    if config.lidar.enabled:
        import platformd.lidar_models
        import platformd.mavlink.proximity  # noqa: F401


async def async_setup(ctx: PlatformContext) -> None:
    """Needs ``ctx.patrol`` (platformd.autonomy) and ``ctx.media`` (platformd.media)."""
    config = ctx.config.mavlink
    if not config.enabled:
        return
    # pymavlink's dialect (a few MB) is imported only on a platform that speaks MAVLink.
    from platformd.mavlink.service import MavlinkService

    key = load_signing_key(Path(config.signing_key_file)) if config.signing_key_file else None
    service = MavlinkService(ctx, key)
    await service.open()
    ctx.mavlink_port = service.port
    # Only the counters that moved: a telemetry datagram has room for little (1200 bytes).
    ctx.telemetry.add_counters(
        "mavlink",
        lambda: {
            name: count
            for name, count in {
                **service.vehicle.counters,
                **service.counters,
                **ctx.egress.counters,
            }.items()
            if count
        },
    )
    ctx.supervisor.start(service)
