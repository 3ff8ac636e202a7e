"""The daemons' settings on a mesh: what a deployment sets, for the test network and the demo."""

from __future__ import annotations

import json
from collections.abc import Sequence

SIGNALING_PORT = 8765
API_PORT = 8780
MULTICAST_GROUP = "239.255.21.0"
"""An organisation-local group (RFC 2365) for beacons in tests and the demo."""


def platform_argv(
    address: str,
    platform_id: str,
    key_file: str,
    destinations: Sequence[str],
    *settings: str,
    sim: bool = True,
) -> list[str]:
    """``python -m platformd`` arguments for a platform whose mesh address is ``address``."""
    argv = ["-m", "platformd", *(["--sim"] if sim else [])]
    for setting in (
        f"platform.id={platform_id}",
        f"security.key_file={key_file}",
        "signaling.host=0.0.0.0",
        f"signaling.advertise_host={address}",
        f"beacon.destinations={json.dumps(list(destinations))}",
        f"beacon.interface_host={address}",
        "velocity.host=0.0.0.0",
        f"velocity.advertise_host={address}",
        f"audio.in_host={address}",
        *settings,
    ):
        argv += ["--set", setting]
    return argv


def station_argv(station_id: str, key_file: str, *settings: str) -> list[str]:
    """``python -m stationd serve`` arguments (its local API stays on the host's loopback)."""
    argv = ["-m", "stationd", "serve"]
    for setting in (f"station.id={station_id}", f"security.key_file={key_file}", *settings):
        argv += ["--set", setting]
    return argv
