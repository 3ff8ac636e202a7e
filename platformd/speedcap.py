"""A teleop speed limit that follows the measured latency (issue 13, item 5; thesis R-11.5).

The seed derives its 150 ms video budget from stopping within 1 m at 6 km/h after a 250 ms
human reaction. Made live: the cap is the speed ``v`` with

    (reaction + video latency + command latency) * v + v² / (2 * braking) = stop distance

(``safety.*``). The override holder's station reports its measured glass-to-glass latency with
``report_latency``. The command latency is the platform's own measurement: the age on arrival
of the oldest velocity packet of the last second (``COMMAND_AGE``: each ``$PVEL`` carries its
send time in the platform's clock as the station estimates it from its heartbeats); a
station whose packets carry no send time reports half its heartbeat round trip instead.
Without a video report, or with one older than ``safety.report_max_age_s``, the cap assumes
``safety.worst_latency_ms``. The cap is published on ``SPEED_CAP``; the motion arbiter clamps
every teleop velocity to it; telemetry's ``speed_cap`` section carries it with its inputs.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Callable
from typing import Any

from brasidas import topics
from brasidas.actor import Actor
from brasidas.codecs.jsonrpc import INVALID_PARAMS, CallContext, RpcError
from brasidas.codecs.telemetry_schema import SpeedLimit
from brasidas.config.platform import SafetySection
from brasidas.messages import SpeedCap
from platformd.context import PlatformContext

KMH = 3.6


def stopping_speed(
    stop_distance_m: float, reaction_s: float, latency_s: float, braking_mps2: float
) -> float:
    """The speed (m/s) that stops within ``stop_distance_m`` after the dead time and braking."""
    dead = reaction_s + latency_s
    return braking_mps2 * (-dead + math.sqrt(dead * dead + 2 * stop_distance_m / braking_mps2))


def compute_cap(
    safety: SafetySection,
    max_speed_kmh: float,
    video_ms: float | None,
    command_ms: float | None,
    *,
    measured: bool = False,
) -> SpeedCap:
    """The cap for these latencies (None: not reported, the worst configured is assumed).
    ``measured``: the command latency is the packets' measured age, not a report."""
    if video_ms is None or command_ms is None:
        latency_ms = safety.worst_latency_ms
        reason = f"no latency report: assuming {latency_ms:.0f} ms"
    else:
        latency_ms = video_ms + command_ms
        source = "command age" if measured else "command"
        reason = f"video {video_ms:.0f} ms + {source} {command_ms:.0f} ms"
    speed = stopping_speed(
        safety.stop_distance_m, safety.reaction_s, latency_ms / 1000, safety.braking_mps2
    )
    cap_kmh = min(max_speed_kmh, speed * KMH)
    if cap_kmh >= max_speed_kmh:
        reason += f": the platform's {max_speed_kmh:g} km/h stops within the distance"
    else:
        reason += f": {cap_kmh:.1f} km/h stops within {safety.stop_distance_m:g} m"
    return SpeedCap(
        fraction=cap_kmh / max_speed_kmh,
        cap_kmh=cap_kmh,
        video_ms=video_ms,
        command_ms=command_ms,
        reason=reason,
    )


class SpeedCapper(Actor):
    """Keeps the holder's latest latency report and the measured command age; publishes the
    cap when it changes."""

    name = "speed_cap"

    def __init__(self, ctx: PlatformContext, clock: Callable[[], float] = time.monotonic) -> None:
        super().__init__(ctx.bus)
        self.ctx = ctx
        self.safety = ctx.config.safety
        self._clock = clock
        self._report: tuple[float, float, float] | None = None
        """Video ms, command ms, and when (clock) — from the override holder."""
        self.cap = self._compute()

    async def run(self) -> None:
        self.subscribe(topics.OVERRIDE_STATE, lambda _state: self.refresh())
        self.subscribe(topics.COMMAND_AGE, lambda _age: self.refresh())
        self.bus.publish(topics.SPEED_CAP, self.cap)
        while True:
            await asyncio.sleep(1.0)
            self.refresh()  # a report ages out

    def report(self, video_ms: float, command_ms: float) -> SpeedCap:
        self._report = (video_ms, command_ms, self._clock())
        self.refresh()
        return self.cap

    def refresh(self) -> None:
        cap = self._compute()
        if cap != self.cap:
            self.cap = cap
            self.bus.publish(topics.SPEED_CAP, cap)

    def _compute(self) -> SpeedCap:
        report = self._report
        if report is not None and self._clock() - report[2] > self.safety.report_max_age_s:
            report = self._report = None
        video, command = (report[0], report[1]) if report is not None else (None, None)
        age = self.bus.last(topics.COMMAND_AGE)
        if age is not None:
            command = age.max_ms
        return compute_cap(
            self.safety,
            self.ctx.config.platform.max_speed_kmh,
            video,
            command,
            measured=age is not None,
        )

    def rpc_report_latency(
        self, call: CallContext, video_ms: float, command_ms: float = 0.0
    ) -> dict[str, Any]:
        """The holder's measured latencies (ms); another session's report is not taken.
        ``command_ms`` counts only while its velocity packets carry no send time."""
        for name, value in (("video_ms", video_ms), ("command_ms", command_ms)):
            if not 0 <= value <= 60_000 or math.isnan(value):
                raise RpcError(INVALID_PARAMS, f"invalid params: {name} must be 0-60000")
        override = self.bus.last(topics.OVERRIDE_STATE)
        session = call.session
        if override is None or not override.engaged or session is None:
            return {"accepted": False, "reason": "no manual override engaged"}
        if override.session_id != session.session_id:
            return {"accepted": False, "reason": f"override held by {override.station_id}"}
        cap = self.report(float(video_ms), float(command_ms))
        return {"accepted": True, "cap_kmh": round(cap.cap_kmh, 2), "reason": cap.reason}

    def section(self) -> SpeedLimit:
        cap = self.cap
        command = None if cap.command_ms is None else round(cap.command_ms, 1)
        return SpeedLimit(round(cap.cap_kmh, 2), cap.video_ms, command, cap.reason)


async def async_setup(ctx: PlatformContext) -> None:
    capper = SpeedCapper(ctx)
    ctx.rpc.add("report_latency", capper.rpc_report_latency)
    ctx.telemetry.register(SpeedLimit, capper.section)
    ctx.supervisor.start(capper)
