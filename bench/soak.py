"""``make soak`` (not in CI): 30 minutes of 20 Hz teleop through the link emulator at 2 % loss,
the NavCam streaming to one station and telemetry to two, on the test network (root only).

A ``--sim`` platform sits behind the emulator (2 % loss both ways); station-1 holds the manual
override and streams ``$PVEL`` at 20 Hz from a slowly varying drive, receives the NavCam and
telemetry; station-2 receives telemetry. Every ``--sample`` seconds it records the daemons' RSS,
the controller's watchdog ``W`` count and the deadman trips (diagnostics, 20.0), and the
longest gaps between ``$PVEL`` frames as they reached the link emulator (the station's stream)
and as it delivered them. At the end: RSS growth from the first sample after warm-up, and
what caused the deadman stops, if any: the station's stream, loss on the link, or nothing seen.

    .venv/bin/python -m bench.soak --minutes 30      # make soak
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from bench.support import rss_mb
from brasidas.netem.core import Profile
from brasidas.netem.netns import TestNetwork, unavailable_reason
from brasidas.netem.relay import DOWN, parse

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from netns import QUIET, Daemon, Fleet, RpcFailed

RESULTS = Path(__file__).resolve().parent / "results"
ROVER = "soak-rover"
VELOCITY_PORT = 21001
DEADMAN = 0.3


async def _retry(fleet: Fleet, station: Daemon, method: str, **params: Any) -> Any:
    for attempt in range(10):
        try:
            return await fleet.api(station, method, **params)
        except RpcFailed:
            if attempt == 9:
                raise
            await asyncio.sleep(0.5)
    return None


async def soak(minutes: float, sample_s: float, warmup_s: float) -> dict[str, Any]:
    scratch = Path(tempfile.mkdtemp(prefix="brasidas-soak-"))
    samples: list[dict[str, Any]] = []
    with TestNetwork("soak") as net:
        fleet = Fleet(net, scratch)
        try:
            rover = net.add_host("rover", impaired=True)
            relay = rover.relay
            assert relay is not None
            loss = Profile(loss=0.02)
            # The longest silence between $PVEL frames, as they reached the emulator (the
            # station's stream) and as it delivered them (after its 2 % loss).
            gaps = {"sent": _Gaps(), "delivered": _Gaps()}

            def arrived(direction: str, frame: bytes, now: float) -> None:
                if direction == DOWN and _is_pvel(frame):
                    gaps["sent"].mark(now)

            def delivered(direction: str, frame: bytes, now: float) -> None:
                if direction == DOWN and _is_pvel(frame):
                    gaps["delivered"].mark(now)

            relay.arrival_taps.append(arrived)
            relay.taps.append(delivered)
            platform = fleet.platform(rover, ROVER, *QUIET[:2], "beacon.max_interval=3.0")
            one = fleet.station(net.add_host("st1"), "station-1")
            two = fleet.station(net.add_host("st2"), "station-2")
            for station in (one, two):
                await fleet.wait_listening(station, "127.0.0.1", 8780, timeout=60)
            await fleet.connect(one, ROVER, 60)
            await fleet.connect(two, ROVER, 60)
            await _retry(
                fleet, one, "command", platform_id=ROVER, group=20, command=0, payload="ON"
            )
            await _retry(fleet, one, "get_telemetry", platform_id=ROVER)
            await _retry(fleet, two, "get_telemetry", platform_id=ROVER)
            await _retry(fleet, one, "receive", platform_id=ROVER, stream="navcam")
            await _retry(fleet, one, "movrd", platform_id=ROVER, engaged=True)
            relay.set_profiles(down=loss, up=loss)
            # What happened before the soak (a controller powered up before its driver opened
            # the port sends W once) is the baseline, not a finding.
            await asyncio.sleep(1.0)
            baseline = _counters(await _retry(fleet, one, "get_telemetry", platform_id=ROVER))
            started = time.monotonic()
            end = started + minutes * 60

            async def drive() -> None:
                while time.monotonic() < end:
                    phase = (time.monotonic() - started) / 20 * 2 * math.pi
                    try:
                        await fleet.api(
                            one,
                            "teleop_set",
                            platform_id=ROVER,
                            linear=round(0.4 * math.sin(phase), 3),
                            angular=round(0.3 * math.cos(phase), 3),
                        )
                    except RpcFailed as err:
                        print(f"teleop_set failed: {err}", flush=True)
                    await asyncio.sleep(0.2)

            async def sample() -> None:
                while time.monotonic() < end:
                    await asyncio.sleep(sample_s)
                    report = await _retry(fleet, one, "get_telemetry", platform_id=ROVER)
                    counters = _counters(report)
                    video = [r for r in await fleet.api(one, "receivers") if "navcam" in r["name"]]
                    row = {
                        "t_s": round(time.monotonic() - started),
                        "platform_rss_mb": rss_mb(platform.process.pid),
                        "station1_rss_mb": rss_mb(one.process.pid),
                        "station2_rss_mb": rss_mb(two.process.pid),
                        "watchdog_w": counters["watchdog_w"] - baseline["watchdog_w"],
                        "deadman_trips": counters["deadman_trips"] - baseline["deadman_trips"],
                        "longest_pvel_gap_sent_ms": gaps["sent"].longest_ms(),
                        "longest_pvel_gap_delivered_ms": gaps["delivered"].longest_ms(),
                        "emulator_socket_drops": relay.stats()["socket_drops"],
                        "navcam_frames": video[0]["frames"] if video else None,
                        "navcam_rtp_lost": video[0].get("rtp_lost") if video else None,
                        "telemetry_loss_pct": report.get("link", {}).get("loss_pct"),
                    }
                    samples.append(row)
                    print(json.dumps(row), flush=True)

            async with asyncio.TaskGroup() as group:
                group.create_task(drive())
                group.create_task(sample())
            link = relay.stats()
        finally:
            fleet.stop()
    warm = [s for s in samples if s["t_s"] >= warmup_s] or samples
    first, last = warm[0], samples[-1]
    trips = last["deadman_trips"]
    # A trip needs DEADMAN without a valid $PVEL: at 2 % loss only a gap on the link explains it.
    if trips == 0:
        cause = "none"
    elif last["longest_pvel_gap_sent_ms"] >= DEADMAN * 1000:
        cause = "the station's stream stalled (not loss)"
    elif last["longest_pvel_gap_delivered_ms"] >= DEADMAN * 1000:
        cause = "loss on the link"
    else:
        cause = "unexplained: no gap of the deadman's length on the link"
    return {
        "minutes": minutes,
        "link": link,
        "platform_rss_growth_mb": round(last["platform_rss_mb"] - first["platform_rss_mb"], 1),
        "station1_rss_growth_mb": round(last["station1_rss_mb"] - first["station1_rss_mb"], 1),
        "station2_rss_growth_mb": round(last["station2_rss_mb"] - first["station2_rss_mb"], 1),
        "watchdog_w": last["watchdog_w"],
        "deadman_trips": trips,
        "longest_pvel_gap_sent_ms": last["longest_pvel_gap_sent_ms"],
        "longest_pvel_gap_delivered_ms": last["longest_pvel_gap_delivered_ms"],
        "emulator_socket_drops": last["emulator_socket_drops"],
        "deadman_cause": cause,
        "navcam_frames": last["navcam_frames"],
        "navcam_rtp_lost": last["navcam_rtp_lost"],
        "samples": len(samples),
        "logs": str(scratch),
    }


class _Gaps:
    def __init__(self) -> None:
        self.last: float | None = None
        self.longest = 0.0

    def mark(self, now: float) -> None:
        if self.last is not None:
            self.longest = max(self.longest, now - self.last)
        self.last = now

    def longest_ms(self) -> int:
        return round(self.longest * 1000)


def _is_pvel(frame: bytes) -> bool:
    datagram = parse(frame)
    return datagram is not None and datagram.destination[1] == VELOCITY_PORT


def _counters(report: dict[str, Any]) -> dict[str, int]:
    """The controller's W count and the deadman trips, from the diagnostics section (20.0)."""
    diagnostics = (report.get("snapshot") or {}).get("diagnostics") or {}
    return {
        "watchdog_w": int((diagnostics.get("motor") or {}).get("watchdog_w") or 0),
        "deadman_trips": int((diagnostics.get("arbiter") or {}).get("deadman_trips") or 0),
    }


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.soak", description=__doc__)
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--sample", type=float, default=30.0, help="seconds between samples")
    parser.add_argument("--warmup", type=float, default=60.0, help="RSS growth counts from here")
    args = parser.parse_args(argv)
    reason = unavailable_reason()
    if reason is not None:
        print(reason, file=sys.stderr)
        return 1
    result = asyncio.run(soak(args.minutes, args.sample, args.warmup))
    text = json.dumps(result, indent=2, sort_keys=True)
    print(text)
    RESULTS.mkdir(exist_ok=True)
    (RESULTS / "soak.json").write_text(text + "\n")
    ok = (
        result["deadman_cause"] in ("none", "loss on the link")
        and not result["watchdog_w"]
        and result["platform_rss_growth_mb"] < 2
        and max(result["station1_rss_growth_mb"], result["station2_rss_growth_mb"]) < 5
    )
    print("soak: PASS" if ok else "soak: FAIL", flush=True)
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
