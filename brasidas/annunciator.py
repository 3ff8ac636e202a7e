"""The annunciator (the seed's Status Display, ch. 11 §4.2): named warnings from snapshots. Pure.

Feed it a snapshot and the link figures with the time; it answers which warnings were raised
and cleared (low battery, controller over-temperature, GPS fix lost, a stale sensor reading,
link degraded, failed streams, connections refused), each with its group 90 code. The station's telemetry receiver
evaluates it on each platform's stream (stationd.telemetry re-exports it), the platform's
MAVLink endpoint on its own telemetry (STATUSTEXT): one set of warnings, worded once.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from brasidas.codecs.commands import CommandCode
from brasidas.codecs.telemetry_schema import (
    Admission,
    Attitude,
    Autonomy,
    Battery,
    Controller,
    Failsafe,
    Gps,
    Perception,
    RecorderStatus,
    Snapshot,
    Streams,
)
from brasidas.config import TelemetryReceiverSection

NOTIFICATION_GROUP = 90
"""Station-only notifications (seed ch. 11 §1)."""
LOW_BATTERY = CommandCode(NOTIFICATION_GROUP, 10)
CONTROLLER_OVER_TEMPERATURE = CommandCode(NOTIFICATION_GROUP, 11)
GPS_FIX_LOST = CommandCode(NOTIFICATION_GROUP, 12)
LINK_DEGRADED = CommandCode(NOTIFICATION_GROUP, 13)
STREAM_FAILED = CommandCode(NOTIFICATION_GROUP, 14)
SENSOR_STALE = CommandCode(NOTIFICATION_GROUP, 15)
PATROL_HOLDING = CommandCode(NOTIFICATION_GROUP, 16)
CONTROL_TAKEN = CommandCode(NOTIFICATION_GROUP, 17)
"""Another station took control of the platform (``movrd --force``, issue 13)."""
LINK_LOST = CommandCode(NOTIFICATION_GROUP, 18)
"""The platform's failsafe ladder stepped (hold, release): it lost this station's link."""
MAP_REFUSED = CommandCode(NOTIFICATION_GROUP, 21)
"""The platform refused its stored map at start (issue 21): it has no map, and says why."""
RECORDER_STOPPED = CommandCode(NOTIFICATION_GROUP, 23)
"""The platform's flight recorder stopped: disk full or failing, its quota (issue 23)."""
CONNECTIONS_REFUSED = CommandCode(NOTIFICATION_GROUP, 24)
"""The platform is refusing many connections from one address (strangers without the fleet
key, issue 19): ``telemetry.refused_warn`` within its 10 s window."""
GPS_REJECTED = CommandCode(NOTIFICATION_GROUP, 30)
"""The lidar localization refuses the GPS: its fixes jumped or dragged away from the lidar
odometry (spoofing, issue 30), until they agree again. Reported only: the patrol's pose does
not use the fused estimate yet."""
FAILED_STREAM_STATES = frozenset({"failed", "error"})


@dataclass(frozen=True)
class Alert:
    """One annunciator warning, active since ``since`` (station clock)."""

    name: str
    code: CommandCode
    message: str
    since: float

    def as_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "code": str(self.code),
            "message": self.message,
            "since": self.since,
        }


@dataclass(frozen=True)
class Change:
    """A warning raised (``active``) or cleared."""

    warning: Alert
    active: bool


class Annunciator:
    """Pure: feed snapshots and link figures with the time; get warnings raised and cleared."""

    def __init__(self, config: TelemetryReceiverSection) -> None:
        self.config = config
        self.active: dict[str, Alert] = {}

    def evaluate(
        self, snapshot: Snapshot, loss_pct: float, silence: float | None, now: float
    ) -> list[Change]:
        """Update the warnings from the latest values; returns what changed."""
        wanted: dict[str, tuple[CommandCode, str]] = {}
        keep: set[str] = set()
        self._battery(snapshot.get(Battery), wanted, keep)
        self._temperature(snapshot.get(Controller), wanted, keep)
        gps = snapshot.get(Gps)
        if gps is not None and not gps.fix:
            lost = gps.lost_for_s
            wanted["gps_fix_lost"] = (
                GPS_FIX_LOST,
                f"GPS fix lost ({lost:.0f} s ago)"
                if lost is not None
                else "no GPS fix yet",  # the receiver has not had one since it started
            )
        for name, reading in (
            ("battery", snapshot.get(Battery)),
            ("gps", gps),
            ("attitude", snapshot.get(Attitude)),
        ):
            if reading is not None and reading.stale and reading.age_ms is not None:
                wanted[f"sensor_stale:{name}"] = (
                    SENSOR_STALE,
                    f"{name} stale ({reading.age_ms / 1000:.0f} s old)",
                )
        perception = snapshot.get(Perception)
        if perception is not None and perception.gps_refusal:
            wanted["gps_rejected"] = (GPS_REJECTED, f"GPS refused: {perception.gps_refusal}")
        link: list[str] = []
        if silence is not None and silence >= self.config.silence_s:
            link.append(f"telemetry silent for {silence:.1f} s")
        if loss_pct > self.config.loss_warn_pct:
            link.append(f"{loss_pct:.0f}% of telemetry lost")
        if link:
            wanted["link_degraded"] = (LINK_DEGRADED, "link degraded: " + ", ".join(link))
        failsafe = snapshot.get(Failsafe)
        if failsafe is not None and failsafe.step != "normal":
            # The platform held (or released) because it lost the holder's link (issue 13).
            wanted["link_lost"] = (
                LINK_LOST,
                f"LINK LOST: platform {failsafe.step}: {failsafe.reason}",
            )
        streams = snapshot.get(Streams)
        for name, state in streams.states.items() if streams is not None else ():
            if state.lower() in FAILED_STREAM_STATES:
                wanted[f"stream_failed:{name}"] = (STREAM_FAILED, f"stream {name} failed")
        autonomy = snapshot.get(Autonomy)
        if autonomy is not None and autonomy.state == "holding":
            wanted["patrol_holding"] = (
                PATROL_HOLDING,
                f"patrol holding: {autonomy.reason or 'no reason given'}",
            )
        if autonomy is not None and autonomy.map_error:
            wanted["map_refused"] = (MAP_REFUSED, f"no map: {autonomy.map_error}")
        recorder = snapshot.get(RecorderStatus)
        if recorder is not None and not recorder.recording and recorder.reason:
            wanted["recorder_stopped"] = (RECORDER_STOPPED, f"recorder stopped: {recorder.reason}")
        admission = snapshot.get(Admission)
        if admission is not None and admission.refused >= self.config.refused_warn:
            wanted["connections_refused"] = (
                CONNECTIONS_REFUSED,
                f"connections refused from {admission.refusing or '?'}: "
                f"{admission.refused} in {admission.window_s:g} s",
            )
        changes: list[Change] = []
        for name in list(self.active):
            if name not in wanted and name not in keep:
                changes.append(Change(self.active.pop(name), False))
        for name, (code, message) in wanted.items():
            current = self.active.get(name)
            if current is None:
                self.active[name] = Alert(name, code, message, now)
                changes.append(Change(self.active[name], True))
            elif current.message != message:
                # Same warning, fresher wording (the figure changed): no new notification.
                self.active[name] = Alert(name, code, message, current.since)
        return changes

    def _battery(self, battery: Battery | None, wanted: dict[str, Any], keep: set[str]) -> None:
        if battery is None:
            return
        volts = battery.volts
        config = self.config
        if battery.level == "low" or (volts is not None and volts < config.battery_low_v):
            figure = f" ({volts:.1f} V)" if volts is not None else ""
            wanted["low_battery"] = (LOW_BATTERY, f"low battery{figure}")
        elif "low_battery" in self.active and volts is not None and volts < config.battery_clear_v:
            keep.add("low_battery")  # hysteresis: not yet recovered

    def _temperature(
        self, controller: Controller | None, wanted: dict[str, Any], keep: set[str]
    ) -> None:
        if controller is None or not controller.temps_c:
            return
        hottest = max(controller.temps_c)
        if hottest >= self.config.controller_max_c:
            wanted["controller_over_temperature"] = (
                CONTROLLER_OVER_TEMPERATURE,
                f"controller over temperature ({hottest:.0f} °C)",
            )
        elif "controller_over_temperature" in self.active and hottest >= (
            self.config.controller_clear_c
        ):
            keep.add("controller_over_temperature")

    def clear_all(self) -> list[Change]:
        changes = [Change(warning, False) for warning in self.active.values()]
        self.active.clear()
        return changes
