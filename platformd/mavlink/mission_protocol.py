"""The MAVLink mission protocol: downloads of the stored mission and fence, uploads item by
item (re-requested when lost, abandoned after :data:`UPLOAD_RETRIES`), MISSION_CLEAR_ALL,
the current item, and GUIDED's mission item. A whole upload becomes an :class:`UploadItems`
for the platform, which answers it with :meth:`MissionProtocol.answer_upload`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas.autonomy.geo import to_e7
from platformd.mavlink import guided, missions
from platformd.mavlink.link import NO_HOLDER, Handler, Link, LinkCore, Upload, UploadState
from platformd.mavlink.missions import FENCE, MAX_ITEMS, MISSION, RALLY, MissionItem
from platformd.mavlink.model import GoTo, Origin, Request, SetCurrent, Severity, UploadItems
from platformd.mavlink.telemetry import mission_current

UPLOAD_RETRY_S = 0.25
"""A mission item not arrived this long after its request is asked for again."""
UPLOAD_RETRIES = 8
"""Requests of one item before the upload is abandoned."""


class MissionProtocol(LinkCore):
    """Mission, fence and rally transfers; the current item."""

    def _init_missions(
        self, upload_window: int, mission_items: Callable[[int], list[MissionItem]]
    ) -> None:
        self.upload_window = upload_window
        """Mission items requested ahead during an upload (1: strictly one at a time)."""
        self.mission_items = mission_items
        """The stored mission (MISSION) or fence (FENCE) as items, for downloads."""

    def answer_upload(self, request: UploadItems, result: int, text: str = "") -> None:
        """MISSION_ACK for an upload (a STATUSTEXT with ``text``: the reason of a refusal)."""
        link = self.links.get(request.peer)
        if link is None:
            return
        if link.upload is not None and link.upload.waiting:
            link.upload.to(UploadState.ANSWERED)
            link.upload = None  # not a newer upload the station started meanwhile
        link.last_ack = (request.mission_type, result)
        self._mission_ack(link, request.system, request.component, result, request.mission_type)
        if text:
            severity = Severity.INFO if result == mavlink.MAV_MISSION_ACCEPTED else Severity.WARNING
            self._statustext_to(link, severity, text)

    def answer_set_current(
        self, request: SetCurrent, result: int, text: str = "", *, holder_system: int = NO_HOLDER
    ) -> None:
        """The answer to a new current item: a COMMAND_ACK when asked by command; accepted,
        MISSION_CURRENT with it at once (the mission protocol's answer); refused, the reason."""
        link = self.links.get(request.peer)
        if link is None:
            return
        accepted = result == mavlink.MAV_RESULT_ACCEPTED
        if request.command is not None:
            self.answer_command(request, result, text, holder_system=holder_system)
        elif text:
            self._statustext_to(link, Severity.INFO if accepted else Severity.WARNING, text)
        if accepted:
            self.state.waypoint = missions.route_index(self.state.waypoint_seqs, request.seq)
            self._send(link, mission_current(self.state))

    def _on_mission_request_list(
        self, link: Link, message: Any, origin: Origin, now: float
    ) -> list[Request]:
        _peer, system, component, _signed = origin
        mission_type = message.mission_type
        if mission_type == RALLY:
            self._send(link, mavlink.MAVLink_mission_count_message(system, component, 0, RALLY))
            return []
        if mission_type not in (MISSION, FENCE):
            self._mission_ack(
                link, system, component, mavlink.MAV_MISSION_UNSUPPORTED, mission_type
            )
            return []
        count = len(self.mission_items(mission_type))
        self._send(
            link, mavlink.MAVLink_mission_count_message(system, component, count, mission_type)
        )
        return []

    def _on_mission_request(
        self, link: Link, message: Any, origin: Origin, now: float
    ) -> list[Request]:
        _peer, system, component, _signed = origin
        mission_type = message.mission_type
        items = self.mission_items(mission_type) if mission_type in (MISSION, FENCE) else []
        if not 0 <= message.seq < len(items):
            self._mission_ack(
                link, system, component, mavlink.MAV_MISSION_INVALID_SEQUENCE, mission_type
            )
            return []
        item = items[message.seq]
        # Always MISSION_ITEM_INT, even to MISSION_REQUEST: QGroundControl ignores MISSION_ITEM.
        self._send(
            link,
            mavlink.MAVLink_mission_item_int_message(
                system,
                component,
                item.seq,
                item.frame,
                item.command,
                item.current,
                item.autocontinue,
                item.param1,
                item.param2,
                item.param3,
                item.param4,
                item.x,
                item.y,
                item.z,
                mission_type,
            ),
        )
        return []

    def _on_mission_count(
        self, link: Link, message: Any, origin: Origin, now: float
    ) -> list[Request]:
        _peer, system, component, _signed = origin
        mission_type, count = message.mission_type, message.count
        refuse = self._mission_refuser(link, system, component, mission_type)
        if mission_type == RALLY and count == 0:
            self._mission_ack(link, system, component, mavlink.MAV_MISSION_ACCEPTED, RALLY)
            return []
        if mission_type not in (MISSION, FENCE):
            refuse(mavlink.MAV_MISSION_UNSUPPORTED, "rally points are not supported")
            return []
        if count > MAX_ITEMS:
            refuse(mavlink.MAV_MISSION_NO_SPACE, f"{count} items: at most {MAX_ITEMS}")
            return []
        return self._upload(link, origin, mission_type, count, "upload", now)

    def _on_mission_item(
        self, link: Link, message: Any, origin: Origin, now: float
    ) -> list[Request]:
        peer, system, component, signed = origin
        upload = link.upload
        mission_type = message.mission_type
        if message.current == guided.GUIDED_ITEM and mission_type == MISSION:
            return self._on_guided_item(link, message, origin)
        if upload is None or not upload.receiving or upload.mission_type != mission_type:
            if link.last_ack is not None and link.last_ack[0] == mission_type:
                # Our ACK was lost and the station repeats its last item: repeat the ACK.
                self._mission_ack(link, system, component, link.last_ack[1], mission_type)
            return []
        if not 0 <= message.seq < upload.count or message.seq in upload.items:
            return []  # a duplicate (answering a repeated request) or out of range
        if message.get_type() == "MISSION_ITEM":
            x, y = to_e7(message.x), to_e7(message.y)
        else:
            x, y = message.x, message.y
        upload.asked.pop(message.seq, None)
        upload.items[message.seq] = MissionItem(
            message.seq,
            message.frame,
            message.command,
            message.param1,
            message.param2,
            message.param3,
            message.param4,
            x,
            y,
            message.z,
            message.autocontinue,
            message.current,
        )
        if len(upload.items) < upload.count:
            self._request_items(link, now)
            return []
        upload.to(UploadState.AWAITING_VERDICT)
        items = tuple(upload.items[seq] for seq in range(upload.count))
        return [UploadItems(peer, system, component, signed, mission_type, items)]

    def _on_guided_item(self, link: Link, message: Any, origin: Origin) -> list[Request]:
        """A mission item with ``current`` 2 (MAVProxy's ``guided LAT LON``, ArduPilot's
        guided waypoint): a go-to; MISSION_ACK says whether it was taken."""
        peer, system, component, signed = origin
        refuse = self._mission_refuser(link, system, component, MISSION)
        target = guided.item_target(message)
        if target is None:
            refuse(mavlink.MAV_MISSION_DENIED, "go to: no latitude, longitude in a global frame")
            return []
        if not self._may_control(signed, "go to", refuse, mavlink.MAV_MISSION_DENIED):
            return []
        return [GoTo(peer, system, component, signed, *target, None)]

    def _on_mission_clear_all(
        self, link: Link, message: Any, origin: Origin, now: float
    ) -> list[Request]:
        _peer, system, component, _signed = origin
        mission_type = message.mission_type
        if mission_type not in (MISSION, FENCE):
            self._mission_ack(link, system, component, mavlink.MAV_MISSION_ACCEPTED, mission_type)
            return []
        return self._upload(link, origin, mission_type, 0, "clear", now)

    def _upload(
        self, link: Link, origin: Origin, mission_type: int, count: int, what: str, now: float
    ) -> list[Request]:
        """An upload of ``count`` items (none: a clear) from a sender that may control: the
        first items asked for, or, with none to ask, the platform's verdict."""
        peer, system, component, signed = origin
        refuse = self._mission_refuser(link, system, component, mission_type)
        if not self._may_control(signed, what, refuse, mavlink.MAV_MISSION_DENIED):
            return []
        upload = self._begin_upload(link, Upload(mission_type, count))
        link.upload_owner = (system, component)
        link.last_ack = None  # a new transfer: the last one's ACK is no longer repeated
        if count:
            self._request_items(link, now)
            return []
        upload.to(UploadState.AWAITING_VERDICT)
        return [UploadItems(peer, system, component, signed, mission_type, ())]

    def _on_mission_set_current(
        self, link: Link, message: Any, origin: Origin, now: float
    ) -> list[Request]:
        peer, system, component, signed = origin

        def refuse(result: int, text: str) -> None:
            self._statustext_to(link, Severity.WARNING, text)

        if not self._may_control(signed, "set current", refuse, mavlink.MAV_RESULT_DENIED):
            return []
        return [SetCurrent(peer, system, component, signed, message.seq, None)]

    def _on_mission_ack(
        self, link: Link, message: Any, origin: Origin, now: float
    ) -> list[Request]:
        return []  # the end of a download: nothing kept per download

    def _begin_upload(self, link: Link, upload: Upload) -> Upload:
        """``upload`` is the link's transfer now; one under way is superseded."""
        if link.upload is not None:
            link.upload.to(UploadState.SUPERSEDED)
        link.upload = upload
        return upload

    def _request_items(self, link: Link, now: float) -> None:
        """Ask for missing items, up to ``upload_window`` outstanding at once; again for any
        asked :data:`UPLOAD_RETRY_S` ago (its request or its answer was lost)."""
        upload = link.upload
        assert upload is not None
        system, component = link.upload_owner
        for seq in upload.missing():
            asked = upload.asked.get(seq)
            if asked is not None and now - asked < UPLOAD_RETRY_S:
                continue
            if asked is None and len(upload.asked) >= self.upload_window:
                break
            if asked is not None:
                upload.retries[seq] = upload.retries.get(seq, 0) + 1
            upload.asked[seq] = now
            self._send(
                link,
                mavlink.MAVLink_mission_request_int_message(
                    system, component, seq, upload.mission_type
                ),
            )

    def _retry_upload(self, link: Link, now: float) -> None:
        upload = link.upload
        if upload is None or not upload.receiving:
            return
        lost = [seq for seq, retries in upload.retries.items() if retries >= UPLOAD_RETRIES]
        if lost and now - upload.asked[lost[0]] >= UPLOAD_RETRY_S:
            system, component = link.upload_owner
            upload.to(UploadState.ABANDONED)
            link.upload = None
            self._mission_ack(
                link,
                system,
                component,
                mavlink.MAV_MISSION_OPERATION_CANCELLED,
                upload.mission_type,
            )
            self._statustext_to(
                link, Severity.WARNING, f"upload abandoned: item {lost[0]} never came"
            )
            return
        self._request_items(link, now)

    def _mission_refuser(
        self, link: Link, system: int, component: int, mission_type: int
    ) -> Callable[[int, str], None]:
        """``refuse(result, text)``: a MISSION_ACK with ``result`` and a warning saying why."""

        def refuse(result: int, text: str) -> None:
            self._mission_ack(link, system, component, result, mission_type)
            self._statustext_to(link, Severity.WARNING, text)

        return refuse

    def _mission_ack(
        self, link: Link, system: int, component: int, result: int, mission_type: int
    ) -> None:
        self._send(
            link, mavlink.MAVLink_mission_ack_message(system, component, result, mission_type)
        )


HANDLERS: dict[str, Handler] = {
    "MISSION_REQUEST_LIST": MissionProtocol._on_mission_request_list,
    "MISSION_REQUEST_INT": MissionProtocol._on_mission_request,
    "MISSION_REQUEST": MissionProtocol._on_mission_request,
    "MISSION_COUNT": MissionProtocol._on_mission_count,
    "MISSION_ITEM_INT": MissionProtocol._on_mission_item,
    "MISSION_ITEM": MissionProtocol._on_mission_item,
    "MISSION_CLEAR_ALL": MissionProtocol._on_mission_clear_all,
    "MISSION_SET_CURRENT": MissionProtocol._on_mission_set_current,
    "MISSION_ACK": MissionProtocol._on_mission_ack,
}
