"""The aggregator: the latest value of every reporting topic, snapshots, and platform health.

The aggregator subscribes to every reporting topic and keeps only the last message of each
(an IMU at 100 Hz costs one assignment per sample); sections are converted to plain values
only when a snapshot is built. Those sections fill ``ctx.telemetry_sources``, so the
``get_telemetry_report`` signaling method and the datagram stream carry the same snapshot.
Command 20.0 switches the diagnostics section on or off. A retained
:class:`~brasidas.messages.PlatformHealth` summarises the state for the beacon's status word.
"""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import socket
import time
from collections.abc import Callable
from datetime import date, datetime
from datetime import time as dtime
from enum import Enum
from pathlib import Path
from typing import Any

from brasidas import topics
from brasidas.actor import Actor
from brasidas.codecs.commands import DIAGNOSTICS, PayloadError, parse_switch
from brasidas.messages import (
    CommandResult,
    ControllerStatus,
    GpsFix,
    GpsFixLost,
    ImuStatus,
    PlatformHealth,
    SessionClosed,
    StreamStatus,
)
from brasidas.status import Battery
from platformd.commands import SystemCommand
from platformd.context import PlatformContext
from platformd.telemetry.stream import StreamSender
from platformd.telemetry.system import MEMINFO, SYSTEM_INFO_MAX_AGE, THERMAL_ROOT, system_info

_LOGGER = logging.getLogger(__name__)


class TelemetryAggregator(Actor):
    """Keeps the latest value of every reporting topic; builds snapshots; runs the streams."""

    name = "telemetry"

    def __init__(
        self,
        ctx: PlatformContext,
        *,
        clock: Callable[[], float] = time.time,
        thermal_root: Path = THERMAL_ROOT,
        meminfo: Path = MEMINFO,
    ) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self._clock = clock
        self._thermal_root = thermal_root
        self._meminfo = meminfo
        self.latest: dict[str, Any] = {}
        """The last report of each subsystem, by section name (see :meth:`subscribe_reports`)."""
        self.stream_states: dict[str, StreamStatus] = {}
        self.diagnostics = False
        self.health: PlatformHealth | None = None
        self.snapshots = 0
        self.sender = StreamSender(ctx.config.platform.id, self.snapshot, clock)
        self._system: tuple[float, dict[str, Any]] | None = None
        self._gps_lost_at: float | None = None

    # ------------------------------------------------------------------ lifecycle

    async def run(self) -> None:
        self.latest.clear()
        self.on_remove(self.ctx.commands.register(self.name, {DIAGNOSTICS: self._command}))
        self.subscribe(topics.SESSION_CLOSED, self._on_session_closed)
        self.subscribe_reports()
        loop = asyncio.get_running_loop()
        transport, _ = await loop.create_datagram_endpoint(
            asyncio.DatagramProtocol, family=socket.AF_INET
        )
        try:
            async with asyncio.TaskGroup() as group:
                self.sender.attach(group, transport)
                group.create_task(self._health_loop(), name="telemetry:health")
        finally:
            self.sender.detach()
            transport.close()

    def subscribe_reports(self) -> None:
        """Keep the last report of every subsystem; retained topics hand theirs over at once.
        (Autonomy has no topic yet: its section stays null until it does.)"""
        self.subscribe(topics.LIGHTS_STATE, self._keep("lights"))
        self.subscribe(topics.CONTROLLER_STATUS, self._keep("controller", health=True))
        self.subscribe(topics.GPS_FIX, self._on_fix)
        self.subscribe(topics.GPS_FIX_LOST, self._on_fix_lost)
        self.subscribe(topics.GPS_STATS, self._keep("gps_stats"))
        self.subscribe(topics.ATTITUDE, self._keep("attitude"))  # ~10 Hz: store only
        self.subscribe(topics.IMU_STATUS, self._keep("imu", health=True))
        self.subscribe(topics.VELOCITY_LINK_STATS, self._keep("velocity_link"))
        self.subscribe(topics.STREAM_STATES, self._on_stream_state)

    def _keep(self, key: str, *, health: bool = False) -> Callable[[Any], None]:
        def keep(message: Any) -> None:
            self.latest[key] = message
            if health:
                self._update_health()

        return keep

    def _on_fix(self, fix: GpsFix) -> None:
        self.latest["gps_fix"] = fix
        self._gps_lost_at = None
        self._update_health()

    def _on_fix_lost(self, lost: GpsFixLost) -> None:
        self.latest["gps_lost"] = lost
        self._gps_lost_at = self._clock()
        self._update_health()

    def _on_stream_state(self, status: StreamStatus) -> None:
        self.stream_states[status.name] = status
        self._update_health()

    # ------------------------------------------------------------------ commands and sessions

    async def _command(self, command: SystemCommand) -> CommandResult:
        """20.0: the diagnostics section on or off. (20.4, the battery monitor, belongs to
        the motor controller's driver: the battery section follows its status's flag.)"""
        try:
            on = parse_switch(command.payload)
        except PayloadError as err:
            return CommandResult(False, str(err))
        self.diagnostics = on
        _LOGGER.info("diagnostics report %s", "on" if on else "off")
        return CommandResult(True, result={"diagnostics": on})

    def _on_session_closed(self, event: SessionClosed) -> None:
        self.sender.stop_stream(event.session_id)

    # ------------------------------------------------------------------ snapshot

    def snapshot(self) -> dict[str, Any]:
        """The full snapshot: mode and override, then every telemetry source."""
        self.snapshots += 1
        override = self.bus.last(topics.OVERRIDE_STATE)
        report: dict[str, Any] = {
            "mode": override.mode.value if override else "autonomous",
            "manual_override": bool(override and override.engaged),
        }
        for name, source in self.ctx.telemetry_sources.items():
            report[name] = source()
        return report

    def sources(self) -> dict[str, Callable[[], Any]]:
        """The sections this aggregator contributes to ``ctx.telemetry_sources``."""
        return {
            "override": self.override_section,
            "lights": lambda: to_plain(self.latest.get("lights")),
            "battery": self.battery_section,
            "controller": self.controller_section,
            "gps": self.gps_section,
            "attitude": self.attitude_section,
            "computer": self.computer_section,
            "link": self.link_section,
            "streams": self.streams_section,
            "autonomy": lambda: to_plain(self.latest.get("autonomy")),
            "diagnostics": self.diagnostics_section,
        }

    def override_section(self) -> dict[str, Any]:
        override = self.bus.last(topics.OVERRIDE_STATE)
        return {
            "engaged": bool(override and override.engaged),
            "station": override.station_id if override else None,
        }

    def battery_section(self) -> dict[str, Any] | None:
        status: ControllerStatus | None = self.latest.get("controller")
        if status is None:
            return None
        volts, monitor = status.battery_volts, status.battery_monitor
        level = None
        if volts is not None and monitor:
            level = battery_level(volts, self.ctx.config.telemetry).name.lower()
        return {"volts": _round(volts, 2), "level": level, "monitor": monitor}

    def controller_section(self) -> dict[str, Any] | None:
        status: ControllerStatus | None = self.latest.get("controller")
        if status is None:
            return None
        return {
            "connected": status.connected,
            "temps_c": _round(to_plain(status.heatsink_c), 1),
            "amps": _round(to_plain(status.motor_amps), 1),
            "internal_volts": _round(status.internal_volts, 2),
        }

    def gps_section(self) -> dict[str, Any] | None:
        fix = self.latest.get("gps_fix")
        stats = self.latest.get("gps_stats")
        if fix is None and stats is None and "gps_lost" not in self.latest:
            return None
        section: dict[str, Any] = dict(to_plain(fix) or {}) if fix is not None else {}
        section["fix"] = fix is not None and self._gps_lost_at is None
        if self._gps_lost_at is not None:
            section["lost_for_s"] = round(self._clock() - self._gps_lost_at, 1)
        if stats is not None:
            section["stats"] = to_plain(stats)
        return section

    def attitude_section(self) -> dict[str, Any] | None:
        attitude = self.latest.get("attitude")
        imu = self.latest.get("imu")
        if attitude is None and imu is None:
            return None
        section: dict[str, Any] = dict(to_plain(attitude) or {}) if attitude is not None else {}
        if imu is not None:
            section["imu"] = to_plain(imu)
        return section

    def computer_section(self) -> dict[str, Any]:
        now = time.monotonic()
        if self._system is None or now - self._system[0] > SYSTEM_INFO_MAX_AGE:
            self._system = (now, system_info(self._thermal_root, self._meminfo))
        return self._system[1]

    def link_section(self) -> dict[str, Any]:
        section: dict[str, Any] = {
            "session_rtt_ms": None,  # measured by the station (heartbeats), not here
            "sessions": self.ctx.session_count,
            "telemetry_streams": len(self.sender.streams),
        }
        if "velocity_link" not in self.ctx.telemetry_sources:
            # The velocity receiver reports its own section when it is there.
            section["velocity"] = to_plain(self.latest.get("velocity_link"))
        return section

    def streams_section(self) -> dict[str, Any]:
        states = {name: status.state for name, status in self.stream_states.items()}
        # Streams that never changed state (idle since start) are still worth listing.
        describe = self.ctx.capabilities.get("streams")
        for stream in describe() if describe is not None else ():
            states.setdefault(str(stream["name"]), stream["state"])
        return states

    def diagnostics_section(self) -> dict[str, Any] | None:
        if not self.diagnostics:
            return None
        return {
            "actor_restarts": dict(self.ctx.supervisor.restarts),
            "bus_delivery_errors": self.bus.delivery_errors,
            "rpc": dict(self.ctx.rpc.counters),
            "commands": dict(self.ctx.commands.counters),
            "auth_failures": self.ctx.sessions.auth_failures,
            "telemetry": self.counters(),
            "gps": to_plain(self.latest.get("gps_stats")),
            "imu": to_plain(self.latest.get("imu")),
            **{name: source() for name, source in self.ctx.diagnostics_sources.items()},
        }

    def counters(self) -> dict[str, int]:
        """Snapshots built, datagrams sent, send errors, sections trimmed."""
        return {"snapshots": self.snapshots, **self.sender.counters}

    # ------------------------------------------------------------------ health

    async def _health_loop(self) -> None:
        # Some inputs (a stream failing silently, GPS age) change without a message.
        while True:
            self._update_health()
            await asyncio.sleep(1.0)

    def compute_health(self) -> PlatformHealth:
        battery = self.battery_section()
        level = Battery[battery["level"].upper()] if battery and battery["level"] else None
        controller = self.controller_section()
        faults: list[str] = []
        if self.ctx.config.motor.enabled and controller is not None and not controller["connected"]:
            faults.append("controller")
        imu: ImuStatus | None = self.latest.get("imu")
        if imu is not None and (imu.error or not imu.ok):
            faults.append("imu")
        states = self.streams_section()
        faults.extend(f"stream:{name}" for name, state in states.items() if state == "failed")
        return PlatformHealth(
            battery=level or Battery.UNKNOWN,
            gps_fix="gps_fix" in self.latest and self._gps_lost_at is None,
            streaming=any(state in ("playing", "streaming") for state in states.values()),
            controller=bool(controller and controller["connected"]),
            fault=bool(faults),
            faults=tuple(faults),
        )

    def _update_health(self) -> None:
        health = self.compute_health()
        if health != self.health:
            self.health = health
            self.bus.publish(topics.PLATFORM_HEALTH, health)


# --------------------------------------------------------------------------- helpers


def battery_level(volts: float, config: Any) -> Battery:
    """Coarse level from the pack voltage and ``telemetry.battery_*_v`` thresholds."""
    if volts < config.battery_low_v:
        return Battery.LOW
    if volts < config.battery_high_v:
        return Battery.MEDIUM
    return Battery.HIGH


def to_plain(value: Any, digits: int = 7) -> Any:
    """A bus message as JSON-like values: dataclasses to dicts, enums to values, floats rounded."""
    if value is None or isinstance(value, bool | int | str):
        return value
    if isinstance(value, float):
        return round(value, digits)
    if isinstance(value, Enum):
        return to_plain(value.value, digits)
    if isinstance(value, datetime | date | dtime):
        return value.isoformat()
    as_dict = getattr(value, "as_dict", None)
    if callable(as_dict):
        return to_plain(as_dict(), digits)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {
            f.name: to_plain(getattr(value, f.name), digits)
            for f in dataclasses.fields(value)
            if not f.name.startswith("_")
        }
    if isinstance(value, dict):
        return {str(k): to_plain(v, digits) for k, v in value.items()}
    if isinstance(value, list | tuple | set | frozenset):
        return [to_plain(item, digits) for item in value]
    return str(value)


def _round(value: Any, digits: int) -> Any:
    if isinstance(value, float):
        return round(value, digits)
    if isinstance(value, list):
        return [_round(item, digits) for item in value]
    return value
