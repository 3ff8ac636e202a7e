"""The MAVLink link core, sans-IO: one :class:`Link` per ground station address, the parse,
the signature verdict, admission of new addresses, the dispatch to handlers, and sending
(signed, and no more to a stranger than it sent). Handlers live in
platformd.mavlink.commands and platformd.mavlink.mission_protocol; the telemetry in
platformd.mavlink.telemetry; platformd.mavlink.vehicle composes them.
"""

from __future__ import annotations

import enum
import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, ClassVar

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas.admission import SourceLedger
from brasidas.states import Transitions
from platformd.mavlink import modes
from platformd.mavlink.missions import MissionItem
from platformd.mavlink.model import (
    CameraInfo,
    GoTo,
    Origin,
    Peer,
    Request,
    SetCurrent,
    SetMode,
    Severity,
    VehicleState,
)
from platformd.mavlink.signing import SignatureCheck, SigningClock, Verdict

_LOGGER = logging.getLogger(__name__)

STATUSTEXT_CHUNK = 50
"""Bytes of text in one STATUSTEXT: a longer text goes in chunks sharing an id."""
NO_HOLDER = 0
MAX_LINKS = 32
"""Ground station addresses kept at once: a flood from made-up source addresses costs a
bounded table (the configured targets are always kept)."""
STRANGER_LINKS = 16
"""Of those, at most this many strangers: a trusted ground station always finds a slot."""


class UploadState(enum.Enum):
    RECEIVING = "receiving"
    """Items are being asked for, one window at a time."""
    AWAITING_VERDICT = "awaiting verdict"
    """All items in (or a clear): the platform decides."""
    ANSWERED = "answered"
    """The platform's MISSION_ACK went out."""
    ABANDONED = "abandoned"
    """An item never came after :data:`~platformd.mavlink.mission_protocol.UPLOAD_RETRIES`."""
    SUPERSEDED = "superseded"
    """The ground station began another transfer on the link."""


UPLOAD_TRANSITIONS = Transitions[UploadState](
    "upload",
    {
        UploadState.RECEIVING: frozenset(
            (UploadState.AWAITING_VERDICT, UploadState.ABANDONED, UploadState.SUPERSEDED)
        ),
        UploadState.AWAITING_VERDICT: frozenset((UploadState.ANSWERED, UploadState.SUPERSEDED)),
    },
)


@dataclass
class Upload:
    """A mission, fence or rally transfer from a ground station, item by item."""

    mission_type: int
    count: int
    items: dict[int, MissionItem] = field(default_factory=dict)
    asked: dict[int, float] = field(default_factory=dict)
    """Items requested and not arrived: when each was last asked for."""
    retries: dict[int, int] = field(default_factory=dict)
    state: UploadState = UploadState.RECEIVING

    @property
    def receiving(self) -> bool:
        return self.state is UploadState.RECEIVING

    @property
    def waiting(self) -> bool:
        """All items in: the platform's verdict is awaited."""
        return self.state is UploadState.AWAITING_VERDICT

    def to(self, state: UploadState) -> None:
        self.state = UPLOAD_TRANSITIONS.check(self.state, state)

    def missing(self) -> list[int]:
        return [seq for seq in range(self.count) if seq not in self.items]


class LinkState(enum.Enum):
    CONFIGURED = "configured"
    """An address in ``mavlink.targets``: kept for good, sent telemetry before it speaks."""
    STRANGER = "stranger"
    """Heard, never trusted: its source address may be anyone's, so it gets no more than
    it gives, and it goes after ``link_timeout`` of silence or for a signed newcomer."""
    TRUSTED = "trusted"
    """Sent a message that could command the robot (signed, or unsigned control allowed)."""
    FORGOTTEN = "forgotten"
    """Out of the vehicle's table (silent, evicted, or nothing valid ever came)."""


LINK_TRANSITIONS = Transitions[LinkState](
    "MAVLink link",
    {
        LinkState.STRANGER: frozenset((LinkState.TRUSTED, LinkState.FORGOTTEN)),
        LinkState.TRUSTED: frozenset((LinkState.FORGOTTEN,)),
    },
)


@dataclass
class Link:
    """One ground station address: its parser, encoder, signing check and transfers."""

    peer: Peer
    decoder: Any
    encoder: Any
    configured: bool
    last_heard: float = -math.inf
    last_trusted: float = -math.inf
    """The last message that could command the robot (signed, or unsigned control allowed):
    only those keep a ground station's session, and the failsafe ladder, alive."""
    gcs_system: int = 0
    check: SignatureCheck | None = None
    upload: Upload | None = None
    upload_owner: tuple[int, int] = (0, 0)
    last_ack: tuple[int, int] | None = None
    """(mission_type, result) of the last upload, resent if the station repeats its last item."""
    state: LinkState = field(init=False)

    def __post_init__(self) -> None:
        self.state = LinkState.CONFIGURED if self.configured else LinkState.STRANGER

    @property
    def stranger(self) -> bool:
        """Not a configured target and never trusted (signed, or unsigned control allowed):
        its source address may be anyone's, so it gets no more than it gives."""
        return self.state is LinkState.STRANGER

    def to(self, state: LinkState) -> None:
        self.state = LINK_TRANSITIONS.check(self.state, state)

    def trusted(self, now: float) -> None:
        """A message that could command the robot came: the link is no stranger's."""
        self.last_trusted = now
        if self.state is LinkState.STRANGER:
            self.to(LinkState.TRUSTED)


Handler = Callable[[Any, "Link", Any, Origin, float], list[Request]]
"""``handler(vehicle, link, message, origin, now)``: what the platform must decide."""


class LinkCore:
    """The links of one MAVLink vehicle (component 1) with its camera (component 100)."""

    handlers: ClassVar[Mapping[str, Handler]] = {}
    """Message type → handler: the composition (platformd.mavlink.vehicle) fills it."""

    def __init__(
        self,
        system_id: int,
        *,
        targets: tuple[Peer, ...] = (),
        key: bytes | None = None,
        allow_unsigned_control: bool = False,
        link_timeout: float = 10.0,
        camera: CameraInfo | None = None,
        wall_clock: Callable[[], float] | None = None,
        ledger: SourceLedger | None = None,
    ) -> None:
        self.system_id = system_id
        self.ledger = ledger if ledger is not None else SourceLedger()
        """Bytes sent on each source address's behalf (brasidas.admission): the platform's."""
        self._now = 0.0
        self.key = key
        self.allow_unsigned_control = allow_unsigned_control
        self.link_timeout = link_timeout
        self.camera = camera
        self.signing_clock = SigningClock(wall_clock)
        self.signatures = SignatureCheck(key, self.signing_clock) if key is not None else None
        """One replay table for the vehicle: every link's signed frames go through it."""
        self._components = {None, 0, modes.VEHICLE_COMPONENT}
        """Target components answered: the vehicle's, the camera's, and broadcasts."""
        if camera is not None:
            self._components.add(modes.CAMERA_COMPONENT)
        self.state = VehicleState()
        self.links: dict[Peer, Link] = {}
        self.outbox: list[tuple[bytes, Peer]] = []
        self.counters: dict[str, int] = dict.fromkeys(
            (
                "received",
                "bad_frames",
                "unsigned",
                "signed",
                "bad_signature",
                "replayed",
                "not_for_us",
                "refused_unsigned",
                "links_forgotten",
                "handler_errors",
                "links_refused",
                "setup_signing_refused",
                "stranger_frames_suppressed",
                "stranger_bytes_suppressed",
                "video_refused",
            ),
            0,
        )
        self._statustext_id = 0
        self._boot: float | None = None
        for peer in targets:
            self._link(peer, configured=True)

    # ------------------------------------------------------------------ input

    def feed(self, data: bytes, peer: Peer, now: float) -> list[Request]:
        """One datagram from ``peer``: answers go to the outbox; returns what needs deciding."""
        if self._boot is None:
            self._boot = now
        self._now = now
        link = self.links.get(peer)
        new = link is None
        if link is None:
            if not self._admit(data):
                self.counters["links_refused"] += 1
                return []
            link = self._link(peer, configured=False)
        if link.stranger:  # its credit, one per address (brasidas.admission.SourceLedger)
            self.ledger.received(peer[0], len(data), now)
        try:
            messages = link.decoder.parse_buffer(data) or []
        except Exception:  # pymavlink raises for a frame it cannot even delimit
            link.decoder.buf = bytearray()
            link.decoder.buf_index = 0
            self.counters["bad_frames"] += 1
            messages = []
        requests: list[Request] = []
        for message in messages:
            if message.get_type() == "BAD_DATA" or isinstance(message, mavlink.MAVLink_unknown):
                # pymavlink hands an unknown message id back before checking its CRC:
                # for random bytes that is noise, not a message.
                self.counters["bad_frames"] += 1
                continue
            signed = self._verdict(link, message)
            if signed is None:
                continue
            self.counters["received"] += 1
            link.last_heard = now
            if signed or self.allow_unsigned_control:
                link.trusted(now)
            try:
                requests.extend(self._handle(link, message, signed, now))
            except Exception:  # one odd message never stops the endpoint
                self.counters["handler_errors"] += 1
                _LOGGER.exception("MAVLink: %s from %s not handled", message.get_type(), peer)
        if not link.configured and link.last_heard == -math.inf:
            self._forget(link)  # nothing valid from a stranger: no state kept for it
        elif new and link.stranger and self._strangers() > STRANGER_LINKS:
            self._forget(link)  # admitted for its signed flag, which did not verify
            self.counters["links_refused"] += 1
        return requests

    def _strangers(self) -> int:
        return sum(1 for link in self.links.values() if link.stranger)

    def _admit(self, data: bytes) -> bool:
        """Room for a new address: strangers share :data:`STRANGER_LINKS` slots; a datagram
        that may be signed (verified once parsed) may also take the slot of the stranger
        heard longest ago."""
        strangers = self._strangers()
        if strangers < STRANGER_LINKS and len(self.links) < MAX_LINKS:
            return True
        maybe_signed = (
            self.signatures is not None and len(data) > 2 and data[0] == 0xFD and data[2] & 1
        )
        if not maybe_signed:
            return False
        if len(self.links) >= MAX_LINKS:
            if not strangers:
                return False
            oldest = min(
                (link for link in self.links.values() if link.stranger),
                key=lambda link: link.last_heard,
            )
            self._forget(oldest)
        return True

    def _verdict(self, link: Link, message: Any) -> bool | None:
        """True signed, False unsigned, None to drop (bad signature, replay)."""
        if link.check is None:
            self.counters["unsigned"] += 1
            return False
        verdict = link.check.check(message.get_msgbuf())
        if verdict is Verdict.SIGNED:
            self.counters["signed"] += 1
            return True
        if verdict is Verdict.UNSIGNED:
            self.counters["unsigned"] += 1
            return False
        self.counters["bad_signature" if verdict is Verdict.BAD_SIGNATURE else "replayed"] += 1
        return None

    def _handle(self, link: Link, message: Any, signed: bool, now: float) -> list[Request]:
        kind = message.get_type()
        system = message.get_srcSystem()
        # MANUAL_CONTROL names its vehicle in ``target``, the others in ``target_system``.
        target = getattr(message, "target_system", getattr(message, "target", None))
        component = getattr(message, "target_component", None)
        if target not in (None, 0, self.system_id) or component not in self._components:
            self.counters["not_for_us"] += 1
            return []
        handler = self.handlers.get(kind)
        if kind == "HEARTBEAT" and message.type == mavlink.MAV_TYPE_GCS:
            link.gcs_system = system
        if handler is None:
            return []
        origin = (link.peer, system, message.get_srcComponent(), signed)
        result: list[Request] = handler(self, link, message, origin, now)
        return result

    def _may_control(
        self, signed: bool, what: str, refuse: Callable[[int, str], None], denied: int
    ) -> bool:
        """Signed, or unsigned control allowed; else ``refuse(denied, reason)``."""
        if signed or self.allow_unsigned_control:
            return True
        self.counters["refused_unsigned"] += 1
        refuse(denied, f"{what} refused: unsigned link (MAVLink signing required for control)")
        return False

    # ------------------------------------------------------------------ output

    def answer_command(
        self,
        request: Request,
        result: int,
        text: str = "",
        *,
        holder_system: int = NO_HOLDER,
        command: int | None = None,
    ) -> None:
        """COMMAND_ACK for ``request`` (and a STATUSTEXT with ``text`` when refused)."""
        link = self.links.get(request.peer)
        if link is None:
            return
        if command is None:
            asked = request.command if isinstance(request, SetMode | SetCurrent | GoTo) else None
            command = asked or 0
        self._send(
            link,
            mavlink.MAVLink_command_ack_message(
                command, result, 0, holder_system, request.system, request.component
            ),
        )
        if text:
            severity = Severity.INFO if result == mavlink.MAV_RESULT_ACCEPTED else Severity.WARNING
            self._statustext_to(link, severity, text)

    def statustext(self, severity: int, text: str) -> None:
        """A warning (or notice) for every ground station (group 90's annunciations)."""
        for link in self.links.values():
            self._statustext_to(link, severity, text)

    def take(self) -> list[tuple[bytes, Peer]]:
        """Empty the outbox."""
        out, self.outbox = self.outbox, []
        return out

    # ------------------------------------------------------------------ time

    def _live_links(self, now: float) -> list[Link]:
        """Forget the strangers not heard for ``link_timeout``."""
        if self._boot is None:
            self._boot = now
        self._now = now
        live: list[Link] = []
        for link in list(self.links.values()):
            if not link.configured and now - link.last_heard > self.link_timeout:
                self._forget(link)
                self.counters["links_forgotten"] += 1
                continue
            live.append(link)
        return live

    def _boot_ms(self, now: float) -> int:
        return int((now - (self._boot or now)) * 1000) & 0xFFFFFFFF

    # ------------------------------------------------------------------ sending

    def _link(self, peer: Peer, *, configured: bool) -> Link:
        decoder = mavlink.MAVLink(None, self.system_id, modes.VEHICLE_COMPONENT)
        decoder.robust_parsing = True
        encoder = mavlink.MAVLink(None, self.system_id, modes.VEHICLE_COMPONENT)
        link = Link(peer, decoder, encoder, configured)
        if self.key is not None:
            link.check = self.signatures
            encoder.signing.secret_key = self.key
            encoder.signing.sign_outgoing = True
            encoder.signing.link_id = len(self.links) & 0xFF
        self.links[peer] = link
        return link

    def _forget(self, link: Link) -> None:
        del self.links[link.peer]
        link.to(LinkState.FORGOTTEN)

    def broadcast(self, message: Any) -> None:
        """A message from another module (platformd.mavlink.proximity) to every link."""
        self._broadcast(message)

    def _broadcast(self, message: Any, component: int = modes.VEHICLE_COMPONENT) -> None:
        for link in self.links.values():
            if link.configured or link.last_heard > -math.inf:
                self._send(link, message, component)

    def _send(self, link: Link, message: Any, component: int = modes.VEHICLE_COMPONENT) -> None:
        self._send_all(link, [message], component)

    def _send_all(
        self, link: Link, messages: list[Any], component: int = modes.VEHICLE_COMPONENT
    ) -> None:
        """All of ``messages`` to ``link``, or, to a stranger out of credit, none (counted)."""
        encoder = link.encoder
        encoder.srcComponent = component
        if encoder.signing.sign_outgoing:
            encoder.signing.timestamp = max(encoder.signing.timestamp, self.signing_clock.now())
        first_seq = encoder.seq
        frames = []
        for message in messages:
            frames.append(message.pack(encoder))
            encoder.seq = (encoder.seq + 1) % 256
        size = sum(len(frame) for frame in frames)
        if not link.stranger:
            self.ledger.trusted_send(link.peer[0], size, "mavlink")
        elif not self.ledger.stranger_send(link.peer[0], size, self._now):
            encoder.seq = first_seq  # what it is sent shows no gap for what it was not
            self.counters["stranger_frames_suppressed"] += len(frames)
            self.counters["stranger_bytes_suppressed"] += size
            return
        self.outbox.extend((frame, link.peer) for frame in frames)

    def _statustext_to(self, link: Link, severity: int, text: str) -> None:
        data = text.encode("utf-8", "replace")[: STATUSTEXT_CHUNK * 4]
        chunks = [data[i : i + STATUSTEXT_CHUNK] for i in range(0, len(data), STATUSTEXT_CHUNK)]
        message_id = 0
        if len(chunks) > 1:
            self._statustext_id = self._statustext_id % 0xFFFF + 1
            message_id = self._statustext_id
            if len(chunks[-1]) == STATUSTEXT_CHUNK:
                chunks.append(b"")  # a full last chunk: an empty one ends the text
        self._send_all(
            link,
            [
                mavlink.MAVLink_statustext_message(severity, chunk, message_id, index)
                for index, chunk in enumerate(chunks)
            ],
        )
