"""The MAVLink 2 vehicle, sans-IO: datagrams in, datagrams and requests out.

:class:`MavlinkVehicle` keeps one :class:`Link` per ground station address (the configured
targets, and whoever talks to it). ``feed(data, peer, now)`` parses a datagram with pymavlink,
checks its signature, answers what needs no decision (telemetry requests, parameters, MAVFTP's
NAK, mission downloads, the upload's item-by-item requests) and returns the
:class:`Request` s the platform must decide: modes, mission and fence uploads, the joystick.
The platform answers each with :meth:`answer_command` or :meth:`answer_upload`.
``tick(now)`` sends the telemetry that is due and re-requests lost mission items. What it sends
is in :attr:`outbox` until :meth:`take` empties it. No sockets, no clock: the transport and the
service (platformd.mavlink.service) do that.

The parts: platformd.mavlink.link (the links, admission, signing, dispatch, sending),
platformd.mavlink.telemetry (the encoders and their rates), platformd.mavlink.commands
(commands, modes, the joystick, parameters, MAVFTP) and platformd.mavlink.mission_protocol
(mission, fence and rally transfers). This module composes them.
"""

from __future__ import annotations

from collections.abc import Callable

from brasidas.admission import SourceLedger
from platformd.mavlink import commands, mission_protocol
from platformd.mavlink.commands import CommandHandlers
from platformd.mavlink.link import (
    MAX_LINKS,
    NO_HOLDER,
    STATUSTEXT_CHUNK,
    STRANGER_LINKS,
    Link,
    Upload,
)
from platformd.mavlink.mission_protocol import UPLOAD_RETRIES, UPLOAD_RETRY_S, MissionProtocol
from platformd.mavlink.missions import MissionItem
from platformd.mavlink.model import (
    SAFETY_COMMANDS,
    CameraInfo,
    GoTo,
    ManualInput,
    Peer,
    Request,
    SetCurrent,
    SetMode,
    Severity,
    StartVideo,
    UploadItems,
    VehicleState,
)
from platformd.mavlink.telemetry import TelemetrySender

__all__ = [
    "MAX_LINKS",
    "NO_HOLDER",
    "SAFETY_COMMANDS",
    "STATUSTEXT_CHUNK",
    "STRANGER_LINKS",
    "UPLOAD_RETRIES",
    "UPLOAD_RETRY_S",
    "CameraInfo",
    "GoTo",
    "Link",
    "ManualInput",
    "MavlinkVehicle",
    "Peer",
    "Request",
    "SetCurrent",
    "SetMode",
    "Severity",
    "StartVideo",
    "Upload",
    "UploadItems",
    "VehicleState",
]


class MavlinkVehicle(CommandHandlers, MissionProtocol, TelemetrySender):
    """One MAVLink vehicle (component 1) with its camera (component 100)."""

    handlers = {**commands.HANDLERS, **mission_protocol.HANDLERS}

    def __init__(
        self,
        system_id: int,
        *,
        targets: tuple[Peer, ...] = (),
        key: bytes | None = None,
        allow_unsigned_control: bool = False,
        link_timeout: float = 10.0,
        upload_window: int = 1,
        rates: tuple[float, float, float] = (1.0, 5.0, 1.0),
        camera: CameraInfo | None = None,
        wall_clock: Callable[[], float] | None = None,
        mission_items: Callable[[int], list[MissionItem]] = lambda mission_type: [],
        ledger: SourceLedger | None = None,
    ) -> None:
        super().__init__(
            system_id,
            targets=targets,
            key=key,
            allow_unsigned_control=allow_unsigned_control,
            link_timeout=link_timeout,
            camera=camera,
            wall_clock=wall_clock,
            ledger=ledger,
        )
        self._init_missions(upload_window, mission_items)
        self._init_telemetry(rates)

    def tick(self, now: float) -> None:
        """Telemetry that is due, mission item re-requests, forgotten links."""
        for link in self._live_links(now):
            self._retry_upload(link, now)
        self._send_due_telemetry(now)
