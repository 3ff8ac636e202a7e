"""Parameters a ground station may set with PARAM_SET, kept across restarts.

Only ArduPilot's ``FENCE_OPTIONS``, and of it only bit 1 (value 2, ``INCLUSION_UNION`` in
ArduPilot's ``AC_Fence``): several inclusion fences in one upload make their union instead
of the area where they all overlap (ArduPilot's default). Its other bits (a mode change after
a breach, margin notices) mean nothing to a rover that holds at its boundary: a value with
them is refused, with the reason, and the old value answered. Every other parameter is the
config's, read-only (:func:`platformd.mavlink.service.config_parameters`).

A value set is written to ``mavlink.parameters_file`` (atomically) before it is answered, so
the next fence upload after a restart is read the same way; a file that is not ours is
reported and the defaults are used.
"""

from __future__ import annotations

import asyncio
import json
import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from brasidas.autonomy.route import write_atomically
from brasidas.files import FileReadError, read_regular_file
from brasidas.security import state_dir
from platformd.mavlink.vehicle import MavlinkVehicle, Request, Severity

_LOGGER = logging.getLogger(__name__)

FENCE_OPTIONS = "FENCE_OPTIONS"
INCLUSION_UNION = 1 << 1
"""ArduPilot's ``FENCE_OPTIONS`` bit 1: inclusion fences make their union."""
SUPPORTED_BITS = {FENCE_OPTIONS: INCLUSION_UNION}
"""Each writable parameter and the bits it may have (ArduPilot's are integers)."""
PARAM_TYPES = {FENCE_OPTIONS: mavlink.MAV_PARAM_TYPE_INT16}
"""As ArduPilot declares them (``AP_Int16``): MAVProxy and QGC send the value in that type."""

STATE_FILE_NAME = "mavlink-parameters.json"
MAX_FILE_BYTES = 4096


def parameters_path(configured: str) -> Path:
    """``mavlink.parameters_file``, or ``$XDG_STATE_HOME/brasidas/mavlink-parameters.json``."""
    return Path(configured).expanduser() if configured else state_dir() / STATE_FILE_NAME


@dataclass(frozen=True)
class SetParameter(Request):
    """PARAM_SET of a writable parameter from a trusted link: the platform decides."""

    name: str
    value: float


def refusal(name: str, value: float) -> str | None:
    """Why ``value`` cannot be ``name``'s (None: it can)."""
    allowed = SUPPORTED_BITS[name]
    if not value.is_integer() or not 0 <= value < 2**15:
        return f"{name} {value:g} refused: a bitmask (a whole number)"
    if int(value) & ~allowed:
        return (
            f"{name} {value:g} refused: only bit 1 (2: inclusion fences as their union) "
            "applies to a rover"
        )
    return None


class WritableParameters:
    """The values ground stations set, and the file that keeps them."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.values: dict[str, float] = dict.fromkeys(SUPPORTED_BITS, 0.0)

    @property
    def fence_union(self) -> bool:
        return int(self.values[FENCE_OPTIONS]) & INCLUSION_UNION != 0

    def listing(self) -> list[tuple[str, float, int]]:
        """As :attr:`VehicleState.params` entries."""
        return [(name, value, PARAM_TYPES[name]) for name, value in self.values.items()]

    def load(self) -> None:
        """Take the saved values (none saved: the defaults). Blocking: call it in a thread.
        Raises :class:`ValueError` naming the file when it is not ours."""
        if not self.path.exists() and not self.path.is_symlink():
            return
        try:
            plain = json.loads(read_regular_file(self.path, "MAVLink parameters", MAX_FILE_BYTES))
        except (FileReadError, ValueError) as err:
            raise ValueError(f"{self.path}: not MAVLink parameters ({err})") from None
        if not isinstance(plain, dict):
            raise ValueError(f"{self.path}: not MAVLink parameters (not an object)")
        for name in SUPPORTED_BITS:
            value = plain.get(name, 0)
            if type(value) not in (int, float) or refusal(name, float(value)) is not None:
                raise ValueError(f"{self.path}: {name} is {value!r}, not one it may be")
            self.values[name] = float(value)

    def save(self) -> None:
        """Blocking: call it in a thread."""
        write_atomically(
            self.path, json.dumps({name: int(value) for name, value in self.values.items()})
        )


# --------------------------------------------------------------------------- the vehicle's hook


def param_request(
    name: str,
    value: float,
    origin: Any,
    refuse: Callable[[int, str], None],
    may_control: Callable[[bool, str, Callable[[int, str], None], int], bool],
) -> list[Request] | None:
    """The vehicle's PARAM_SET of ``name``: None when it is not writable (the vehicle answers
    read-only); a trusted link's request, or nothing when refused (``refuse`` said why)."""
    if name not in SUPPORTED_BITS:
        return None
    peer, system, component, signed = origin
    if not may_control(signed, f"PARAM_SET {name}", refuse, 0):
        return []
    return [SetParameter(peer, system, component, signed, name, float(value))]


# --------------------------------------------------------------------------- the service's side


class Endpoint(Protocol):
    """What this needs of the MAVLink service (platformd.mavlink.service)."""

    vehicle: MavlinkVehicle
    parameters: WritableParameters

    def refused(self, request: Request, what: str) -> str | None: ...


async def restore(endpoint: Endpoint) -> None:
    """Take the saved values before the endpoint binds, and list them with the config's."""
    parameters = endpoint.parameters
    try:
        await asyncio.to_thread(parameters.load)
    except ValueError as err:
        _LOGGER.error("MAVLink: %s; parameters start at their defaults", err)
    endpoint.vehicle.state.params = [
        *(entry for entry in endpoint.vehicle.state.params if entry[0] not in SUPPORTED_BITS),
        *parameters.listing(),
    ]


async def decide(endpoint: Endpoint, request: SetParameter) -> None:
    """Set, save, then answer every link with the new value (ArduPilot's PARAM_VALUE after a
    change); refused, the asker gets the old value and the reason."""
    vehicle = endpoint.vehicle
    parameters = endpoint.parameters
    name, value = request.name, request.value
    reason = endpoint.refused(request, f"PARAM_SET {name}") or refusal(name, value)
    if reason is None and value != parameters.values[name]:
        old = parameters.values[name]
        parameters.values[name] = value
        try:
            await asyncio.to_thread(parameters.save)
        except OSError as err:
            parameters.values[name] = old
            reason = f"{name} not set: cannot save it to {parameters.path} ({err.strerror})"
    vehicle.state.params = [
        (known, parameters.values[known], kind) if known == name else (known, current, kind)
        for known, current, kind in vehicle.state.params
    ]
    if reason is not None:
        vehicle.answer_param(request, name, reason)
        return
    _LOGGER.info("MAVLink: %s set to %g by %s", name, value, request.peer)
    vehicle.answer_param(request, name)
    what = "their union" if parameters.fence_union else "where they all overlap"
    vehicle.statustext(Severity.INFO, f"{name} {value:g}: several inclusion fences: {what}")
