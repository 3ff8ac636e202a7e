"""The telemetry snapshot projected onto the recording channels (issue 32): one pure mapping
that Foxglove live and the recorder both use, so a client and a recording name the same
things the same way.

:func:`channel_messages` takes the snapshot published before and the one now (the typed
:class:`~brasidas.codecs.telemetry_schema.Snapshot`, the one read model) and returns what to
log: each changed section on its telemetry channel, the well-known channels it feeds
(positions, the motor command and its source, the route, the lidar's
scan and fused pose) and the ``/state`` changes it shows.
No I/O, no clock: the time is a parameter.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING

from brasidas.codecs.telemetry_schema import (
    Autonomy,
    Failsafe,
    Gps,
    LidarView,
    Motion,
    Override,
    Pose,
    Section,
    SectionValue,
    Snapshot,
    Streams,
)
from brasidas.recording import schemas
from brasidas.recording.schemas import ChannelSpec

if TYPE_CHECKING:  # numpy: not for every reader of the projection
    from brasidas.perception.view import GridImage

HDOP_TO_SIGMA_M = 2.5
"""A fix's position uncertainty (1 sigma, m) per unit of HDOP (the recorder's and Foxglove's)."""


@dataclass(frozen=True)
class ChannelMessage:
    """One message to log: the channel, its encoded payload, its log time (ns)."""

    spec: ChannelSpec
    data: bytes
    time_ns: int


@dataclass(frozen=True)
class StateChange:
    """A ``/state`` record: what changed, to which state, held by which station, why."""

    what: str
    state: str
    station: str | None = None
    reason: str = ""

    def encode(self) -> bytes:
        return schemas.encode_json(
            {"what": self.what, "state": self.state, "station": self.station, "reason": self.reason}
        )


def section_channel(cls: type[Section]) -> ChannelSpec:
    """A section's own telemetry channel (``/telemetry/<name>``)."""
    return schemas.telemetry_channel(cls)


def encode_section(value: Section) -> bytes:
    """A section's message on its channel: every field, by name (JSON)."""
    return schemas.encode_section(value)


def section_message(value: Section, time_ns: int) -> ChannelMessage:
    """A section on its own telemetry channel."""
    return ChannelMessage(section_channel(type(value)), encode_section(value), time_ns)


def derived_messages(value: Section, time_ns: int) -> list[ChannelMessage]:
    """The well-known channels a section feeds: GPS and pose positions, the motor command with
    the source it came from (the motion section's mode), the planned route."""
    if isinstance(value, Gps):
        if value.fix and value.lat is not None and value.lon is not None:
            sigma = value.hdop * HDOP_TO_SIGMA_M if value.hdop is not None else None
            data = schemas.encode_location(time_ns, value.lat, value.lon, value.alt, sigma)
            return [ChannelMessage(schemas.GPS, data, time_ns)]
    elif isinstance(value, Pose):
        if value.lat is not None and value.lon is not None:
            data = schemas.encode_location(time_ns, value.lat, value.lon, None, value.sigma_m)
            return [ChannelMessage(schemas.POSE, data, time_ns)]
    elif isinstance(value, Motion):
        # The motion section's velocity is the last motor command the arbiter published; its
        # mode says which source it came from (the override's $PVEL, or cmd_vel).
        data = schemas.encode_velocity(float(value.linear), float(value.angular))
        source = schemas.TELEOP_VELOCITY if value.mode == "teleop" else schemas.AUTONOMY_VELOCITY
        return [
            ChannelMessage(schemas.MOTOR_COMMAND, data, time_ns),
            ChannelMessage(source, data, time_ns),
        ]
    elif isinstance(value, Autonomy):
        path = [(float(p[0]), float(p[1])) for p in value.path if len(p) >= 2]
        return [ChannelMessage(schemas.ROUTE, schemas.encode_path(path), time_ns)]
    elif isinstance(value, LidarView):
        out = []
        if value.ranges_dm:
            scan = schemas.encode_sector_scan(time_ns, value.ranges_dm)
            out.append(ChannelMessage(schemas.LIDAR_SCAN, scan, time_ns))
        if value.fused_lat is not None and value.fused_lon is not None:
            fix = schemas.encode_location(time_ns, value.fused_lat, value.fused_lon, None, None)
            out.append(ChannelMessage(schemas.FUSED_POSE, fix, time_ns))
        return out
    return []


def grid_message(image: GridImage, time_ns: int) -> ChannelMessage:
    """The occupancy grid on ``/grid`` (foxglove.Grid), as the recorder and Foxglove live
    publish it."""
    data = schemas.encode_grid(
        time_ns, image.x_m, image.y_m, image.cell_m, image.columns, image.cells
    )
    return ChannelMessage(schemas.OCCUPANCY_GRID, data, time_ns)


def state_changes(value: Section) -> list[StateChange]:
    """The ``/state`` records a section shows (the caller logs those that changed)."""
    if isinstance(value, Failsafe):
        holder = value.controller
        return [
            StateChange("failsafe", value.step, None, value.reason),
            StateChange("control", "held" if holder else "free", holder),
        ]
    if isinstance(value, Override):
        return [
            StateChange("override", "engaged" if value.engaged else "disengaged", value.station)
        ]
    if isinstance(value, Streams):
        return [StateChange(f"stream:{name}", str(state)) for name, state in value.states.items()]
    if isinstance(value, Autonomy):
        return [StateChange("patrol", value.state, None, value.reason)]
    return []


def changed_sections(
    previous: Snapshot | None, now: Snapshot
) -> list[tuple[Section, Section | None]]:
    """Every section in ``now`` with its value in ``previous`` (None when new or changed
    from an error), in the snapshot's order."""
    before: Mapping[type[Section], SectionValue] = previous.sections if previous else {}
    out: list[tuple[Section, Section | None]] = []
    for cls, value in now.sections.items():
        if isinstance(value, Section):
            old = before.get(cls)
            out.append((value, old if isinstance(old, Section) else None))
    return out


def channel_messages(
    previous: Snapshot | None,
    now: Snapshot,
    time_ns: int,
    *,
    again: frozenset[type[Section]] = frozenset(),
) -> tuple[list[ChannelMessage], list[StateChange]]:
    """What ``now`` adds to ``previous``: the messages of every section that changed (and of
    those in ``again``, re-published unchanged so a late subscriber gets them), and the state
    records of the changed ones (only those whose record differs from the previous one's)."""
    messages: list[ChannelMessage] = []
    changes: list[StateChange] = []
    for value, old in changed_sections(previous, now):
        changed = value != old
        if not changed and type(value) not in again:
            continue
        messages.append(section_message(value, time_ns))
        messages.extend(derived_messages(value, time_ns))
        if changed:
            before = set(state_changes(old)) if old is not None else set()
            changes.extend(c for c in state_changes(value) if c not in before)
    return messages, changes
