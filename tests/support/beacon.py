"""Beacons for tests: a sample one and a platform config that sends them to a test's port."""

from __future__ import annotations

from brasidas.codecs.beacon import Beacon
from brasidas.status import Battery, StatusWord


def sample(**changes: object) -> Beacon:
    fields: dict[str, object] = {
        "platform_id": "brasidas-rover-12",
        "signaling_url": "http://10.144.23.117:8765",
        "status": StatusWord(movrd=True, main_lights=True, battery=Battery.MEDIUM, gps_fix=True),
        "boot": 0xDEADBEEF,
        "seq": 123456,
        "position": (37.9415123, 23.6530456),
    }
    fields.update(changes)
    return Beacon(**fields)  # type: ignore[arg-type]


def beacon_config(port: int, *extra: str) -> list[str]:
    return [
        "beacon.enabled=true",
        f"beacon.port={port}",
        'beacon.destinations=["127.0.0.1"]',
        "beacon.listen=false",  # the collector holds the port alone
        *extra,
    ]
