"""The MAVLink vehicle's commands (COMMAND_LONG/INT, SET_MODE), the joystick (MANUAL_CONTROL,
RC_CHANNELS_OVERRIDE), GUIDED targets, parameters (read-only), MAVFTP's refusal and
SETUP_SIGNING's. What changes the robot becomes a :class:`Request` for the platform.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from platformd.mavlink import ftp, guided, manual, modes, protocol_version
from platformd.mavlink.link import Handler, Link, LinkCore
from platformd.mavlink.missions import command_name
from platformd.mavlink.model import (
    SAFETY_COMMANDS,
    GoTo,
    ManualInput,
    Origin,
    Request,
    SetCurrent,
    SetMode,
    Severity,
    StartVideo,
)
from platformd.mavlink.modes import FlightMode
from platformd.mavlink.telemetry import (
    autopilot_version,
    camera_information,
    home_position,
    video_stream_information,
)


class CommandHandlers(LinkCore):
    """Commands, modes, the joystick, parameters, MAVFTP and SETUP_SIGNING."""

    safety_request: Callable[..., list[Request]] | None = None
    """Arm, disarm, terminate (:data:`SAFETY_COMMANDS`): platformd.mavlink.arming's
    ``safety_request``, set by the service; unsupported without it."""

    param_request: Callable[..., list[Request] | None] | None = None
    """PARAM_SET of a writable parameter: platformd.mavlink.parameters' ``param_request``."""

    def answer_param(self, request: Request, name: str, text: str = "") -> None:
        """PARAM_VALUE of ``name`` as it is now: with ``text`` (a refusal's reason, also sent)
        to the asker; without (a change), to every ground station."""
        index = self._param_index(name, -1)
        link = self.links.get(request.peer)
        if index is None or link is None:
            return
        if text:
            self._send(link, self._param_value(index))
            self._statustext_to(link, Severity.WARNING, text)
        else:
            self._broadcast(self._param_value(index))

    def _on_command(self, link: Link, message: Any, origin: Origin, now: float) -> list[Request]:
        command = message.command
        target_component = message.target_component
        is_camera = target_component == modes.CAMERA_COMPONENT
        peer, system, component, signed = origin
        params = (message.param1, message.param2, message.param3, message.param4)
        ack = self._acker(link, command, system, component, is_camera)
        if command == mavlink.MAV_CMD_REQUEST_MESSAGE:
            return self._request_message(link, int(params[0]), ack, origin)
        if command == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            ack(mavlink.MAV_RESULT_ACCEPTED)
            self._send(link, autopilot_version(self.system_id))
            return []
        if command == mavlink.MAV_CMD_GET_HOME_POSITION:
            return self._request_message(link, mavlink.MAVLINK_MSG_ID_HOME_POSITION, ack, origin)
        if command == mavlink.MAV_CMD_REQUEST_CAMERA_INFORMATION:
            return self._request_message(
                link, mavlink.MAVLINK_MSG_ID_CAMERA_INFORMATION, ack, origin
            )
        if command == mavlink.MAV_CMD_REQUEST_VIDEO_STREAM_INFORMATION:
            return self._request_message(
                link, mavlink.MAVLINK_MSG_ID_VIDEO_STREAM_INFORMATION, ack, origin
            )
        if command in (mavlink.MAV_CMD_DO_SET_MODE, mavlink.MAV_CMD_MISSION_START):
            if command == mavlink.MAV_CMD_MISSION_START:
                mode: FlightMode | None = FlightMode.AUTO
            elif not int(params[0]) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
                ack(mavlink.MAV_RESULT_UNSUPPORTED, "set a custom mode: MANUAL, HOLD or AUTO")
                return []
            else:
                mode = modes.mode_named(int(params[1]))
            if mode is None:
                ack(
                    mavlink.MAV_RESULT_UNSUPPORTED,
                    f"mode {int(params[1])} is not a Brasidas mode (MANUAL, HOLD, AUTO, RTL, GUIDED)",
                )
                return []
            if not self._may_control(signed, "set mode", ack, mavlink.MAV_RESULT_DENIED):
                return []
            return [SetMode(peer, system, component, signed, mode, command)]
        if command == mavlink.MAV_CMD_DO_REPOSITION:
            target = guided.reposition_target(message)
            if target is None:
                ack(mavlink.MAV_RESULT_DENIED, "go to: no latitude, longitude in a global frame")
                return []
            if not self._may_control(signed, "go to", ack, mavlink.MAV_RESULT_DENIED):
                return []
            return [GoTo(peer, system, component, signed, *target, command)]
        if command == mavlink.MAV_CMD_DO_SET_MISSION_CURRENT:
            if not self._may_control(signed, "set current", ack, mavlink.MAV_RESULT_DENIED):
                return []
            seq = int(params[0]) if math.isfinite(params[0]) else -1
            return [SetCurrent(peer, system, component, signed, seq, command)]
        if command in SAFETY_COMMANDS and self.safety_request is not None:
            return self.safety_request(command, params, origin, ack, self._may_control)
        if command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            # Ground stations set many intervals at connect: the ACK says no, without a text
            # for each (the rates are the platform's, mavlink.*_hz).
            ack(mavlink.MAV_RESULT_DENIED)
            return []
        ack(
            mavlink.MAV_RESULT_UNSUPPORTED,
            f"command {command_name(command)} is not supported",
        )
        return []

    def _acker(
        self, link: Link, command: int, system: int, component: int, is_camera: bool
    ) -> Callable[..., None]:
        def ack(result: int, text: str = "") -> None:
            """COMMAND_ACK from the addressed component; a STATUSTEXT with ``text``."""
            self._send(
                link,
                mavlink.MAVLink_command_ack_message(command, result, 0, 0, system, component),
                modes.CAMERA_COMPONENT if is_camera else modes.VEHICLE_COMPONENT,
            )
            if text:
                self._statustext_to(link, Severity.WARNING, text)

        return ack

    def _request_message(
        self, link: Link, message_id: int, ack: Callable[..., None], origin: Origin
    ) -> list[Request]:
        peer, system, component, signed = origin
        reply: Any = None
        source = modes.VEHICLE_COMPONENT
        requests: list[Request] = []
        if message_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            reply = autopilot_version(self.system_id)
        elif message_id == protocol_version.MSG_ID:
            reply = protocol_version.protocol_version()
        elif message_id == mavlink.MAVLINK_MSG_ID_HOME_POSITION:
            reply = home_position(self.state)
            if reply is None:
                ack(mavlink.MAV_RESULT_TEMPORARILY_REJECTED, "no home yet: waiting for a GPS fix")
                return []
        elif message_id in (
            mavlink.MAVLINK_MSG_ID_CAMERA_INFORMATION,
            mavlink.MAVLINK_MSG_ID_VIDEO_STREAM_INFORMATION,
        ):
            if self.camera is None:
                ack(mavlink.MAV_RESULT_UNSUPPORTED, "no camera on this platform")
                return []
            source = modes.CAMERA_COMPONENT
            if message_id == mavlink.MAVLINK_MSG_ID_CAMERA_INFORMATION:
                reply = camera_information(self.camera)
            else:
                reply = video_stream_information(self.camera)
                # Video is megabytes for a 44-byte request from an address anyone can claim:
                # only for a signed request or a configured target (issue 26, defect 2).
                if self.ledger.admits_stream(peer[0], signed or link.configured):
                    requests.append(StartVideo(peer, system, component, signed))
                else:
                    self.counters["video_refused"] += 1
                    self._statustext_to(
                        link,
                        Severity.WARNING,
                        "video: only for a signed ground station or one in mavlink.targets",
                    )
        if reply is None:
            ack(mavlink.MAV_RESULT_UNSUPPORTED)  # asked at connect for optional ones: no text
            return []
        ack(mavlink.MAV_RESULT_ACCEPTED)
        self._send(link, reply, source)
        return requests

    def _on_set_mode(self, link: Link, message: Any, origin: Origin, now: float) -> list[Request]:
        peer, system, component, signed = origin
        ack = self._acker(link, mavlink.MAVLINK_MSG_ID_SET_MODE, system, component, False)
        mode = modes.mode_named(message.custom_mode)
        if mode is None or not message.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            ack(
                mavlink.MAV_RESULT_UNSUPPORTED,
                f"mode {message.custom_mode} is not a Brasidas mode (MANUAL, HOLD, AUTO, RTL, GUIDED)",
            )
            return []
        if not self._may_control(signed, "set mode", ack, mavlink.MAV_RESULT_DENIED):
            return []
        return [SetMode(peer, system, component, signed, mode, mavlink.MAVLINK_MSG_ID_SET_MODE)]

    def _steering_allowed(self, signed: bool) -> bool:
        """The joystick and a go-to by position target have no answer: unsigned ones (unless
        allowed) are only counted."""
        if signed or self.allow_unsigned_control:
            return True
        self.counters["refused_unsigned"] += 1
        return False

    def _on_manual_control(
        self, link: Link, message: Any, origin: Origin, now: float
    ) -> list[Request]:
        peer, system, component, signed = origin
        if not self._steering_allowed(signed):
            return []
        linear = _axis(message.x)
        angular = -_axis(message.r)  # MAVLink's r is yaw to the right; ours turns left
        return [ManualInput(peer, system, component, signed, linear, angular)]

    def _on_position_target(
        self, link: Link, message: Any, origin: Origin, now: float
    ) -> list[Request]:
        """SET_POSITION_TARGET_GLOBAL_INT: a go-to (no answer but the mode and the position)."""
        peer, system, component, signed = origin
        if not self._steering_allowed(signed):
            return []
        target = guided.position_target(message)
        if target is None:
            return []
        return [GoTo(peer, system, component, signed, *target, None)]

    def _on_rc_override(
        self, link: Link, message: Any, origin: Origin, now: float
    ) -> list[Request]:
        """RC_CHANNELS_OVERRIDE: the joystick as ArduRover's channels (see manual.py)."""
        peer, system, component, signed = origin
        if not self._steering_allowed(signed):
            return []
        linear, angular = manual.rc_velocity(message)
        return [ManualInput(peer, system, component, signed, linear, angular)]

    def _on_param_request_list(
        self, link: Link, message: Any, origin: Origin, now: float
    ) -> list[Request]:
        params = self.state.params
        for index in range(len(params)):
            self._send(link, self._param_value(index))
        return []

    def _on_param_request_read(
        self, link: Link, message: Any, origin: Origin, now: float
    ) -> list[Request]:
        index = self._param_index(message.param_id, message.param_index)
        if index is not None:
            self._send(link, self._param_value(index))
        return []

    def _on_param_set(self, link: Link, message: Any, origin: Origin, now: float) -> list[Request]:
        index = self._param_index(message.param_id, -1)
        name = _text(message.param_id)
        if index is None:
            self._statustext_to(link, Severity.WARNING, f"no parameter {name}")
            return []
        if self.param_request is not None:  # platformd.mavlink.parameters: the writable ones

            def refuse(_result: int, text: str) -> None:
                self.answer_param(Request(*origin), name, text)

            asked = self.param_request(name, message.param_value, origin, refuse, self._may_control)
            if asked is not None:
                return asked
        # The unchanged value tells the client the write did not take.
        self._send(link, self._param_value(index))
        self._statustext_to(
            link,
            Severity.WARNING,
            f"{name} is read-only: change it in the platform's config file",
        )
        return []

    def _param_index(self, param_id: Any, index: int) -> int | None:
        params = self.state.params
        if 0 <= index < len(params):
            return index
        name = _text(param_id)
        for position, (known, _value, _type) in enumerate(params):
            if known == name:
                return position
        return None

    def _param_value(self, index: int) -> Any:
        name, value, param_type = self.state.params[index]
        return mavlink.MAVLink_param_value_message(
            name.encode(), value, param_type, len(self.state.params), index
        )

    def _on_setup_signing(
        self, link: Link, message: Any, origin: Origin, now: float
    ) -> list[Request]:
        # Never from a ground station, signed or not: the key is the platform's own config.
        self.counters["setup_signing_refused"] += 1
        self._statustext_to(
            link,
            Severity.WARNING,
            "SETUP_SIGNING refused: the key is the platform's mavlink.signing_key_file",
        )
        return []

    def _on_ftp(self, link: Link, message: Any, origin: Origin, now: float) -> list[Request]:
        _peer, system, component, _signed = origin
        answer = ftp.reply(bytes(message.payload))
        if answer is not None:
            self._send(
                link,
                mavlink.MAVLink_file_transfer_protocol_message(0, system, component, list(answer)),
            )
        return []


HANDLERS: dict[str, Handler] = {
    "COMMAND_LONG": CommandHandlers._on_command,
    "COMMAND_INT": CommandHandlers._on_command,
    "SET_MODE": CommandHandlers._on_set_mode,
    "MANUAL_CONTROL": CommandHandlers._on_manual_control,
    "RC_CHANNELS_OVERRIDE": CommandHandlers._on_rc_override,
    "SET_POSITION_TARGET_GLOBAL_INT": CommandHandlers._on_position_target,
    "PARAM_REQUEST_LIST": CommandHandlers._on_param_request_list,
    "PARAM_REQUEST_READ": CommandHandlers._on_param_request_read,
    "PARAM_SET": CommandHandlers._on_param_set,
    "FILE_TRANSFER_PROTOCOL": CommandHandlers._on_ftp,
    "SETUP_SIGNING": CommandHandlers._on_setup_signing,
}


def _axis(value: int) -> float:
    return max(-1.0, min(1.0, value / 1000.0))


def _text(value: Any) -> str:
    if isinstance(value, bytes):
        value = value.decode("ascii", "replace")
    return str(value).split("\0", 1)[0]
