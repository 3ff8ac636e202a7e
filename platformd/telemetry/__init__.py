"""Telemetry: the latest-value snapshot of the platform, and the push stream to stations.

:mod:`.aggregator` builds the platform's sections (schema:
:mod:`brasidas.codecs.telemetry_schema`) from the bus's retained values, takes snapshots of
every registered section (``ctx.telemetry``, :mod:`brasidas.telemetry_sources`) and publishes
the platform's health; :mod:`.stream` pushes authenticated datagrams
(:mod:`brasidas.codecs.telemetry`) to each station session; :mod:`.system` reads the
computer's figures; :mod:`.methods` holds the signaling methods ``request_telemetry`` and
``stop_telemetry``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from platformd.telemetry.aggregator import TelemetryAggregator, battery_level
from platformd.telemetry.methods import (
    MAX_RATE_HZ,
    TelemetryMethods,
    allowed_host,
    stream_parameters,
)
from platformd.telemetry.stream import StreamSender, TelemetryStream
from platformd.telemetry.system import cpu_temperature, system_info

if TYPE_CHECKING:
    from platformd.context import PlatformContext

__all__ = [
    "MAX_RATE_HZ",
    "StreamSender",
    "TelemetryAggregator",
    "TelemetryMethods",
    "TelemetryStream",
    "allowed_host",
    "async_setup",
    "battery_level",
    "cpu_temperature",
    "stream_parameters",
    "system_info",
]


async def async_setup(ctx: PlatformContext) -> None:
    aggregator = TelemetryAggregator(ctx)
    aggregator.register()
    methods = TelemetryMethods(ctx, aggregator.sender)
    ctx.rpc.add("request_telemetry", methods.request_telemetry)
    ctx.rpc.add("stop_telemetry", methods.stop_telemetry)
    ctx.capabilities.register(
        "telemetry",
        lambda: {
            "rate_hz": ctx.config.telemetry.rate_hz,
            "push": True,
            **stream_parameters(ctx.fleet_key is not None),
        },
    )
    ctx.supervisor.start(aggregator)
