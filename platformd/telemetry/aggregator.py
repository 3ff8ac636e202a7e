"""The aggregator: builds the platform's sections, snapshots, and the platform's health.

The sections are built from the bus's retained values (``bus.last``) when a snapshot is
taken, each as its :mod:`~brasidas.codecs.telemetry_schema` dataclass: an IMU at 100 Hz costs
nothing here. The aggregator registers its sections in ``ctx.telemetry`` beside those of
other subsystems; the ``get_telemetry_report`` signaling method and the datagram stream carry
the same snapshot. Every sensor reading carries its age, and is *stale* when older than a
few periods of its sensor. Command 20.0 switches the diagnostics section on or off. A
retained :class:`~brasidas.messages.PlatformHealth` summarises the state for the beacon's
status word.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING

from brasidas import topics
from brasidas.actor import Actor
from brasidas.codecs.commands import DIAGNOSTICS, PayloadError, parse_switch
from brasidas.codecs.telemetry_schema import (
    Attitude,
    Battery,
    Computer,
    Controller,
    Diagnostics,
    Gps,
    GpsReader,
    Imu,
    Lights,
    Link,
    Override,
    Section,
    SectionValue,
    Streams,
    age_ms,
    snapshot_to_wire,
    stale_after,
)
from brasidas.messages import (
    CommandResult,
    ControlState,
    GpsFix,
    GpsFixLost,
    PlatformHealth,
    SessionClosed,
    StreamStatus,
)
from brasidas.status import Battery as BatteryLevel
from platformd.automation import report_switch
from platformd.commands import SystemCommand
from platformd.telemetry.stream import StreamSender
from platformd.telemetry.system import MEMINFO, SYSTEM_INFO_MAX_AGE, THERMAL_ROOT, system_info

if TYPE_CHECKING:
    from brasidas.config import TelemetrySection
    from platformd.context import PlatformContext

_LOGGER = logging.getLogger(__name__)

ATTITUDE_MAX_HZ = 10.0
"""The IMU publishes its attitude at most this often, whatever its sample rate."""
LIVE_HEARTBEATS = 3
"""A session that missed this many heartbeats gets no telemetry until it calls again."""
GPS_DEFAULT_HZ = 1.0
"""Epochs per second of a real receiver (the NEO-6M's default)."""


class TelemetryAggregator(Actor):
    """Builds the platform's sections from the bus; takes snapshots; runs the streams."""

    name = "telemetry"

    def __init__(
        self,
        ctx: PlatformContext,
        *,
        clock: Callable[[], float] = time.time,
        monotonic: Callable[[], float] = time.monotonic,
        thermal_root: Path = THERMAL_ROOT,
        meminfo: Path = MEMINFO,
    ) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self._clock = clock
        self._monotonic = monotonic
        self._thermal_root = thermal_root
        self._meminfo = meminfo
        self.stream_states: dict[str, StreamStatus] = {}
        self.diagnostics = False
        self.health: PlatformHealth | None = None
        self.snapshots = 0
        self.sender = StreamSender(
            ctx.config.platform.id,
            lambda: snapshot_to_wire(self.snapshot()),
            clock,
            self.session_live,
        )
        self._system: tuple[float, Computer] | None = None
        self._gps_lost_at: float | None = None
        self._gps_lost = False
        config = ctx.config
        self._stale_controller = stale_after(config.motor.poll_hz)
        gps_hz = config.gps.sim_rate_hz if config.sim.enabled else GPS_DEFAULT_HZ
        self._stale_gps = stale_after(gps_hz)
        self._stale_attitude = stale_after(min(config.imu.rate_hz, ATTITUDE_MAX_HZ))

    def register(self) -> None:
        """Register this aggregator's sections in ``ctx.telemetry``."""
        sources = self.ctx.telemetry
        sources.register(Override, self.override_section)
        sources.register(Lights, self.lights_section)
        sources.register(Battery, self.battery_section)
        sources.register(Controller, self.controller_section)
        sources.register(Gps, self.gps_section)
        sources.register(Attitude, self.attitude_section)
        sources.register(Computer, self.computer_section)
        sources.register(Link, self.link_section)
        sources.register(Streams, self.streams_section)
        sources.register(Diagnostics, self.diagnostics_section)

    # ------------------------------------------------------------------ lifecycle

    async def run(self) -> None:
        self.on_remove(self.ctx.commands.register(self.name, {DIAGNOSTICS: self._command}))
        report_switch(self.bus, "diagnostics", self.diagnostics)
        self.subscribe(topics.SESSION_CLOSED, self._on_session_closed)
        self.subscribe(topics.CONTROL_STATE, self._on_control)
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
        """Follow what the health summary and the unretained topics need; the rest is read
        from the bus's retained values when a snapshot is built."""
        self.subscribe(topics.CONTROLLER_STATUS, lambda _: self._update_health())
        self.subscribe(topics.IMU_STATUS, lambda _: self._update_health())
        self.subscribe(topics.GPS_FIX, self._on_fix)
        self.subscribe(topics.GPS_FIX_LOST, self._on_fix_lost)
        self.subscribe(topics.STREAM_STATES, self._on_stream_state)

    def _on_fix(self, fix: GpsFix) -> None:
        self._gps_lost_at = None
        self._update_health()

    def _on_fix_lost(self, lost: GpsFixLost) -> None:
        self._gps_lost = True
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
        report_switch(self.bus, "diagnostics", on)
        _LOGGER.info("diagnostics report %s", "on" if on else "off")
        return CommandResult(True, result={"diagnostics": on})

    def session_live(self, session_id: str) -> bool:
        """Whether ``session_id`` was heard from (a call, or its velocity datagrams) within
        three heartbeat intervals, and never less than ``failsafe.hold_after`` — the failsafe
        ladder's notion of a lost link. A silent session's telemetry pauses."""
        session = self.ctx.session(session_id)
        if session is None:
            return False
        config = self.ctx.config
        silent_after = max(
            LIVE_HEARTBEATS * config.signaling.heartbeat_interval, config.failsafe.hold_after
        )
        return self._monotonic() - max(session.last_seen, session.last_velocity) < silent_after

    def _on_control(self, control: ControlState) -> None:
        # Control changed hands (a takeover, its holder's session ended): every station hears
        # it now, not at its next snapshot or heartbeat — the previous holder must stop driving.
        # Once the bus has delivered the change to everyone (the override released first).
        if control.previous_station_id is not None:
            asyncio.get_running_loop().call_soon(self.sender.push)

    def _on_session_closed(self, event: SessionClosed) -> None:
        self.sender.stop_stream(event.session_id)

    # ------------------------------------------------------------------ snapshot

    def snapshot(self) -> dict[type[Section], SectionValue]:
        """Every registered section, built now (a failing one is that section's error)."""
        self.snapshots += 1
        return self.ctx.telemetry.build()

    def override_section(self) -> Override:
        override = self.bus.last(topics.OVERRIDE_STATE)
        if override is None:
            return Override()
        return Override(override.mode.value, override.engaged, override.station_id)

    def lights_section(self) -> Lights | None:
        lights = self.bus.last(topics.LIGHTS_STATE)
        return None if lights is None else Lights(lights.main, lights.positional, lights.errors)

    def battery_section(self) -> Battery | None:
        status = self.bus.last(topics.CONTROLLER_STATUS)
        if status is None:
            return None
        volts, monitor = status.battery_volts, status.battery_monitor
        level = None
        if volts is not None and monitor:
            level = battery_level(volts, self.ctx.config.telemetry).name.lower()
        age, stale = self._age(status.stamp, self._stale_controller, volts is not None)
        return Battery(_round(volts, 2), level, monitor, age, stale)

    def controller_section(self) -> Controller | None:
        status = self.bus.last(topics.CONTROLLER_STATUS)
        if status is None:
            return None
        polled = status.heatsink_c is not None or status.motor_amps is not None
        age, stale = self._age(status.stamp, self._stale_controller, polled)
        return Controller(
            status.connected,
            _pair(status.heatsink_c, 1),
            _pair(status.motor_amps, 1),
            _round(status.internal_volts, 2),
            status.error,
            age,
            stale,
        )

    def gps_section(self) -> Gps | None:
        fix = self.bus.last(topics.GPS_FIX)
        stats = self.bus.last(topics.GPS_STATS)
        if fix is None and stats is None and not self._gps_lost:
            return None
        reader = None
        if stats is not None:
            reader = GpsReader(
                stats.connected,
                stats.sentences,
                stats.fixes,
                {reason: count for reason, count in stats.dropped.items() if count},
                stats.incomplete_epochs,
                stats.error,
            )
        lost_for = None
        if self._gps_lost_at is not None:
            lost_for = round(self._clock() - self._gps_lost_at, 1)
        if fix is None:
            return Gps(fix=False, lost_for_s=lost_for, stats=reader)
        age, stale = self._age(fix.stamp, self._stale_gps, True)
        return Gps(
            fix=self._gps_lost_at is None,
            lat=round(fix.latitude, 7),
            lon=round(fix.longitude, 7),
            alt=_round(fix.altitude_m, 1),
            speed=_round(fix.speed_mps, 2),
            course=_round(fix.course_deg, 1),
            quality=fix.quality,
            sats=fix.satellites,
            hdop=_round(fix.hdop, 2),
            time=fix.time,
            lost_for_s=lost_for,
            stats=reader,
            age_ms=age,
            stale=stale,
        )

    def attitude_section(self) -> Attitude | None:
        attitude = self.bus.last(topics.ATTITUDE)
        status = self.bus.last(topics.IMU_STATUS)
        if attitude is None and status is None:
            return None
        imu = None
        if status is not None:
            imu = Imu(
                status.ok,
                status.error,
                _round(status.temperature_c, 1),
                status.samples,
                status.read_errors,
                status.calibrated,
                status.fifo_overflows,
            )
        if attitude is None:
            return Attitude(imu=imu)
        age, stale = self._age(attitude.stamp, self._stale_attitude, True)
        return Attitude(
            round(attitude.roll_deg, 2),
            round(attitude.pitch_deg, 2),
            round(attitude.yaw_deg, 2),
            (
                round(attitude.w, 4),
                round(attitude.x, 4),
                round(attitude.y, 4),
                round(attitude.z, 4),
            ),
            imu,
            age,
            stale,
        )

    def computer_section(self) -> Computer:
        now = time.monotonic()
        if self._system is None or now - self._system[0] > SYSTEM_INFO_MAX_AGE:
            info = system_info(self._thermal_root, self._meminfo)
            load = info["load"]
            computer = Computer(
                info["cpu_temp_c"],
                None if load is None else tuple(load),
                info["mem_free_mb"],
                info["mem_total_mb"],
            )
            self._system = (now, computer)
        return self._system[1]

    def link_section(self) -> Link:
        return Link(self.ctx.session_count, len(self.sender.streams))

    def streams_section(self) -> Streams:
        return Streams(self._stream_states())

    def diagnostics_section(self) -> Diagnostics | None:
        if not self.diagnostics:
            return None
        sources = self.ctx.telemetry
        return Diagnostics(
            actor_restarts=dict(self.ctx.supervisor.restarts),
            bus_delivery_errors=self.bus.delivery_errors,
            rpc=dict(self.ctx.rpc.counters),
            commands=dict(self.ctx.commands.counters),
            auth_failures=self.ctx.sessions.auth_failures,
            telemetry=self.counters(),
            section_errors=dict(sources.errors),
            subsystems={name: dict(counters()) for name, counters in sources.counters.items()},
        )

    def counters(self) -> dict[str, int]:
        """Snapshots built, datagrams sent, send errors, sections trimmed."""
        return {"snapshots": self.snapshots, **self.sender.counters}

    def _age(
        self, stamp: float, stale_s: float | None, has_reading: bool
    ) -> tuple[int | None, bool]:
        """The reading's age in ms and whether it is stale (None, False without a reading)."""
        if not has_reading:
            return None, False
        age = age_ms(self._monotonic(), stamp)
        return age, stale_s is not None and age > stale_s * 1000

    def _stream_states(self) -> dict[str, str]:
        states = {name: status.state for name, status in self.stream_states.items()}
        # Streams that never changed state (idle since start) are still worth listing.
        media = self.ctx.media
        for stream in media.describe_streams() if media is not None else ():
            states.setdefault(str(stream["name"]), str(stream["state"]))
        return states

    # ------------------------------------------------------------------ health

    async def _health_loop(self) -> None:
        # Some inputs (a stream failing silently, GPS age) change without a message.
        while True:
            self._update_health()
            await asyncio.sleep(1.0)

    def compute_health(self) -> PlatformHealth:
        status = self.bus.last(topics.CONTROLLER_STATUS)
        level = BatteryLevel.UNKNOWN
        if status is not None and status.battery_volts is not None and status.battery_monitor:
            level = battery_level(status.battery_volts, self.ctx.config.telemetry)
        connected = status is not None and status.connected
        faults: list[str] = []
        if self.ctx.config.motor.enabled and status is not None and not connected:
            faults.append("controller")
        imu = self.bus.last(topics.IMU_STATUS)
        if imu is not None and (imu.error or not imu.ok):
            faults.append("imu")
        states = self._stream_states()
        faults.extend(f"stream:{name}" for name, state in states.items() if state == "failed")
        return PlatformHealth(
            battery=level,
            gps_fix=self.bus.last(topics.GPS_FIX) is not None and self._gps_lost_at is None,
            streaming=any(state in ("playing", "streaming") for state in states.values()),
            controller=connected,
            fault=bool(faults),
            faults=tuple(faults),
        )

    def _update_health(self) -> None:
        try:
            health = self.compute_health()
        except Exception:  # never let a bad report stop the snapshots (counted in the log)
            _LOGGER.exception("platform health not computed")
            return
        if health != self.health:
            self.health = health
            self.bus.publish(topics.PLATFORM_HEALTH, health)


# --------------------------------------------------------------------------- helpers


def battery_level(volts: float, config: TelemetrySection) -> BatteryLevel:
    """Coarse level from the pack voltage and ``telemetry.battery_*_v`` thresholds."""
    if volts < config.battery_low_v:
        return BatteryLevel.LOW
    if volts < config.battery_high_v:
        return BatteryLevel.MEDIUM
    return BatteryLevel.HIGH


def _round(value: float | None, digits: int) -> float | None:
    return None if value is None else round(value, digits)


def _pair(values: tuple[float, ...] | None, digits: int) -> tuple[float, ...] | None:
    # from a list, not a generator: the tuple is made at its size (see telemetry_schema._fields)
    return None if values is None else tuple([round(v, digits) for v in values])
