"""The platform beacon (R-16): sans-IO encoder and decoder.

A beacon is one UDP datagram: a msgpack array followed by a truncated HMAC-SHA256 tag over
that array, made with the fleet key::

    [version, platform_id, signaling_url, status_word, boot, seq, lat_e7, lon_e7] + tag

``status_word`` is :class:`brasidas.status.StatusWord`; latitude and longitude are signed
integers in units of 1e-7 degree (about 1 cm; msgpack packs them in 5 bytes each) or nil
when the position is unknown. ``boot`` is the platform's boot number (kept on disk, it only
grows: platformd.boot_counter) and ``seq`` counts beacons within that boot, so a receiver
refuses a replayed beacon: an earlier boot, or the same boot with a sequence not newer. A
lower boot is taken only once the platform has announced it over an authenticated session
(:func:`boot_proof`, :meth:`ReplayGuard.announce`): a platform whose counter was reset.
The whole datagram stays under :data:`MAX_BEACON` bytes.

Without a fleet key (``--insecure``) the tag is absent; a receiver that has a key refuses
such beacons.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import msgpack

from brasidas import security
from brasidas.autonomy.geo import to_e7
from brasidas.status import StatusWord

VERSION = 1
TAG_LENGTH = 8
"""64 bits: a forger gets one try per datagram, and beacons are worthless seconds later."""
MAX_BEACON = 100
_TAG_DOMAIN = b"brasidas-beacon-v1"


class BeaconError(ValueError):
    """A datagram that is not a beacon we accept; ``reason`` is a :class:`DropReason`."""

    def __init__(self, reason: DropReason, detail: str = "") -> None:
        super().__init__(f"{reason.value}: {detail}" if detail else reason.value)
        self.reason = reason


class DropReason(Enum):
    MALFORMED = "malformed"
    VERSION = "version"
    UNSIGNED = "unsigned"
    BAD_TAG = "bad_tag"
    REPLAY = "replay"
    OVERSIZE = "oversize"


@dataclass(frozen=True)
class Beacon:
    platform_id: str
    signaling_url: str
    status: StatusWord
    boot: int
    seq: int
    position: tuple[float, float] | None = None
    """(latitude, longitude) in degrees, when the platform knows it."""


def encode(beacon: Beacon, key: bytes | None) -> bytes:
    """The datagram for ``beacon``; raises ValueError if it would exceed :data:`MAX_BEACON`."""
    lat = lon = None
    if beacon.position is not None:
        lat, lon = to_e7(beacon.position[0]), to_e7(beacon.position[1])
    body: bytes = msgpack.packb(
        [
            VERSION,
            beacon.platform_id,
            beacon.signaling_url,
            beacon.status.encode(),
            beacon.boot & 0xFFFFFFFF,
            beacon.seq & 0xFFFFFFFF,
            lat,
            lon,
        ]
    )
    datagram = body + (_tag(key, body) if key is not None else b"")
    if len(datagram) > MAX_BEACON:
        raise ValueError(
            f"beacon is {len(datagram)} bytes (limit {MAX_BEACON}): shorten the platform id "
            "or the signaling URL"
        )
    return datagram


def decode(datagram: bytes, key: bytes | None) -> Beacon:
    """Parse and authenticate one datagram; raises :class:`BeaconError` with the reason."""
    if len(datagram) > MAX_BEACON:
        raise BeaconError(DropReason.OVERSIZE, f"{len(datagram)} bytes")
    unpacker = msgpack.Unpacker(raw=False, strict_map_key=True, max_buffer_size=MAX_BEACON)
    unpacker.feed(datagram)
    try:
        fields = unpacker.unpack()
    except (msgpack.OutOfData, ValueError, msgpack.ExtraData) as err:
        raise BeaconError(DropReason.MALFORMED, str(err) or type(err).__name__) from None
    except Exception as err:  # msgpack raises several unrelated types on garbage
        raise BeaconError(DropReason.MALFORMED, type(err).__name__) from None
    body_length = unpacker.tell()
    body, tag = datagram[:body_length], datagram[body_length:]
    if not isinstance(fields, list) or not fields:
        raise BeaconError(DropReason.MALFORMED, "not an array")
    if fields[0] != VERSION:
        raise BeaconError(DropReason.VERSION, f"version {fields[0]!r}")
    if key is not None:
        if not tag:
            raise BeaconError(DropReason.UNSIGNED)
        if not security.verify(_tag(key, body), tag):
            raise BeaconError(DropReason.BAD_TAG)
    if len(fields) != 8:
        raise BeaconError(DropReason.MALFORMED, f"{len(fields)} fields")
    _, platform_id, url, word, boot, seq, lat, lon = fields
    if not (isinstance(platform_id, str) and platform_id and isinstance(url, str) and url):
        raise BeaconError(DropReason.MALFORMED, "id and url must be strings")
    for name, number in (("status", word), ("boot", boot), ("seq", seq)):
        if not isinstance(number, int) or isinstance(number, bool) or not 0 <= number < 2**32:
            raise BeaconError(DropReason.MALFORMED, f"{name} must be a 32-bit unsigned integer")
    position: tuple[float, float] | None = None
    if lat is not None or lon is not None:
        if not (isinstance(lat, int) and isinstance(lon, int)):
            raise BeaconError(DropReason.MALFORMED, "position must be integers")
        if not (-900_000_000 <= lat <= 900_000_000 and -1_800_000_000 <= lon <= 1_800_000_000):
            raise BeaconError(DropReason.MALFORMED, "position out of range")
        position = (lat / 1e7, lon / 1e7)
    try:
        status = StatusWord.decode(word)
    except ValueError as err:
        raise BeaconError(DropReason.MALFORMED, str(err)) from None
    return Beacon(platform_id, url, status, boot, seq, position)


def _tag(key: bytes, body: bytes) -> bytes:
    return security.tag(key, _TAG_DOMAIN, body, length=TAG_LENGTH)


_BOOT_DOMAIN = b"brasidas-boot-v1"


def boot_proof(key: bytes, platform_id: str, boot: int, station_nonce: str) -> str:
    """The platform's signed announcement of its boot number to one connecting station (the
    station's fresh nonce: it cannot be replayed to another connection), in hex."""
    return security.tag(key, _BOOT_DOMAIN, platform_id, str(boot), station_nonce).hex()


class ReplayGuard:
    """Per platform: refuses a beacon whose (boot, seq) is not newer than the last accepted:
    an earlier boot is a replay too (boots only grow), unless announced."""

    def __init__(self) -> None:
        self._last: dict[str, tuple[int, int]] = {}

    def check(self, beacon: Beacon) -> None:
        last = self._last.get(beacon.platform_id)
        if last is not None and beacon.boot < last[0]:
            raise BeaconError(DropReason.REPLAY, f"boot {beacon.boot} after boot {last[0]}")
        if last is not None and last[0] == beacon.boot and beacon.seq <= last[1]:
            raise BeaconError(DropReason.REPLAY, f"seq {beacon.seq} after {last[1]}")
        self._last[beacon.platform_id] = (beacon.boot, beacon.seq)

    def announce(self, platform_id: str, boot: int) -> None:
        """The platform said, authenticated, that it runs boot ``boot``: its beacons of that
        boot are taken from now on, even if lower than one seen (its counter was reset);
        earlier boots' are not."""
        last = self._last.get(platform_id)
        if last is None or last[0] != boot:
            self._last[platform_id] = (boot, -1)

    def forget(self, platform_id: str) -> None:
        self._last.pop(platform_id, None)
