"""MAVLink arming and stopping (issue 27): ``MAV_CMD_COMPONENT_ARM_DISARM`` (force-disarm
21196), ``MAV_CMD_DO_FLIGHTTERMINATION`` and HOLD from a ground station that does not hold
control.

Stopping never needs control: any trusted link (signed, or unsigned control allowed) may
disarm, terminate or HOLD; arming needs control. An untrusted link gets ``DENIED``. The
vehicle (sans-IO) turns the command into a :class:`SafetyCommand`; the service decides it
through :mod:`platformd.arming`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas import topics
from brasidas.bus import Bus
from brasidas.codecs.telemetry_schema import Arming, Snapshot
from brasidas.messages import ArmingState, SafetyNotice
from platformd.context import PlatformContext
from platformd.mavlink.vehicle import MavlinkVehicle, Request, VehicleState
from platformd.session_table import Session


class Endpoint(Protocol):
    """What this needs of the MAVLink service (platformd.mavlink.service)."""

    ctx: PlatformContext
    bus: Bus
    vehicle: MavlinkVehicle
    prearm_said: tuple[str, ...]

    def session_for(self, request: Request) -> Session: ...

    def holder_system(self) -> int: ...

    def flush(self) -> None: ...


FORCE_DISARM_MAGIC = 21196.0
"""param2 of MAV_CMD_COMPONENT_ARM_DISARM that forces a disarm (ArduPilot, PX4)."""
COMMANDS = (mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_DO_FLIGHTTERMINATION)


@dataclass(frozen=True)
class SafetyCommand(Request):
    """Arm, disarm (``force``) or terminate (an emergency stop: disarmed at once)."""

    action: str
    force: bool
    command: int


def safety_request(
    command: int,
    params: tuple[float, float, float, float],
    origin: Any,
    ack: Callable[..., None],
    may_control: Callable[[bool, str, Callable[[int, str], None], int], bool],
) -> list[Request]:
    """The vehicle's hook for :data:`COMMANDS`: a request for a trusted link, else DENIED."""
    peer, system, component, signed = origin
    if command == mavlink.MAV_CMD_DO_FLIGHTTERMINATION:
        if params[0] < 0.5:
            ack(mavlink.MAV_RESULT_ACCEPTED)  # terminate off: nothing to do
            return []
        action, force = "terminate", True
    elif params[0] >= 0.5:
        action, force = "arm", False
    else:
        action, force = "disarm", params[1] == FORCE_DISARM_MAGIC
    if not may_control(signed, action, ack, mavlink.MAV_RESULT_DENIED):
        return []
    return [SafetyCommand(peer, system, component, signed, action, force, command)]


async def decide(service: Endpoint, request: SafetyCommand) -> None:
    """Arm needs control and the pre-arm checks; disarm and terminate are anyone's."""
    arming = service.ctx.arming
    vehicle = service.vehicle
    if arming is None:
        vehicle.answer_command(request, mavlink.MAV_RESULT_UNSUPPORTED, "no arming here")
        return
    session = service.session_for(request)
    if request.action == "arm":
        refusal = service.ctx.authority.refusal(session, "arm")
        if refusal is None:
            refusal = arming.arm(session.station_id)
            result = mavlink.MAV_RESULT_FAILED
        else:
            result = mavlink.MAV_RESULT_DENIED
        if refusal is not None:
            vehicle.answer_command(
                request,
                result,
                refusal,
                command=request.command,
                holder_system=service.holder_system(),
            )
            return
        vehicle.answer_command(request, mavlink.MAV_RESULT_ACCEPTED, command=request.command)
        return
    await arming.stop(session, request.action, force=request.force)
    vehicle.answer_command(request, mavlink.MAV_RESULT_ACCEPTED, command=request.command)


async def hold_for_anyone(service: Endpoint, request: Any) -> bool:
    """HOLD from a trusted ground station that does not hold control: a stop (True), as
    a station observer's; False when the sender holds (or may claim) control."""
    arming = service.ctx.arming
    authority = service.ctx.authority
    session = service.session_for(request)
    if arming is None or authority.controller is None or authority.holds(session):
        return False
    await arming.stop(session, "hold")
    service.vehicle.answer_command(request, mavlink.MAV_RESULT_ACCEPTED)
    return True


def follow(service: Endpoint) -> Callable[[], None]:
    """The heartbeat's armed flag from ``ARMING_STATE``; each safety notice (pre-arm
    refusals, the countdown, stops) as a STATUSTEXT. Returns the way to unsubscribe."""
    state = service.vehicle.state
    state.armed = False
    state.prearm_ok = False

    def on_arming(arming: ArmingState) -> None:
        state.armed = arming.armed

    def on_notice(notice: SafetyNotice) -> None:
        service.vehicle.statustext(notice.severity, notice.text)
        service.flush()

    removers = (
        service.bus.subscribe(topics.ARMING_STATE, on_arming),
        service.bus.subscribe(topics.SAFETY_NOTICES, on_notice),
    )

    def remove() -> None:
        for remover in removers:
            remover()

    return remove


def refresh(service: Endpoint, snapshot: Snapshot) -> None:
    """SYS_STATUS's pre-arm bit from the telemetry's ``arming`` section (once a second); a
    STATUSTEXT for each pre-arm check that starts failing, as ArduPilot's ``PreArm: ...``."""
    section = snapshot.sections.get(Arming)
    if not isinstance(section, Arming):
        return
    state: VehicleState = service.vehicle.state
    state.prearm_ok = section.ready
    for reason in section.prearm:
        if reason not in service.prearm_said:
            service.vehicle.statustext(mavlink.MAV_SEVERITY_WARNING, reason)
    service.prearm_said = section.prearm
