"""The MAVLink endpoint (issue 22): what one ground station costs and how fast it is answered.

- ``gcs_cpu_percent``: the endpoint's own CPU (thread time in its handler, ticks and sends) in
  an in-process ``--sim`` platform with one ground station heartbeating at 1 Hz and receiving
  the default telemetry, as % of one core over 10 s (target < 1 %); beside it a
  ``brasidas-platform --sim`` process's CPU with the endpoint off and on (their difference is
  within the machine's noise).
- ``command_ack_*``: COMMAND_LONG (DO_SET_MODE HOLD: the platform's decision path) to its
  COMMAND_ACK on loopback, 200 in a row.
- ``upload_100_*``: a 100-item mission upload (MISSION_COUNT to MISSION_ACK, the ground station
  re-sending what times out as QGroundControl does) on loopback, and across the namespace link
  emulator at 10 % loss and 50 ± 20 ms each way (target ≤ 3 s; root only).
- ``manual_control_to_serial_*``: MANUAL_CONTROL at 20 Hz to the first byte of the resulting
  AX3500 command at a pty tap, beside ``$PVEL``'s (``bench velocity``).
- ``qgc_connect_to_params_*`` (issue 29): QGroundControl's connect sequence (AUTOPILOT_VERSION,
  PROTOCOL_VERSION, MAVFTP ``@PARAM/param.pck`` then PARAM_REQUEST_LIST) from the first request
  to "parameters complete", on loopback (target ≤ 2 s). The missions uploaded above hold a
  DO_CHANGE_SPEED after every waypoint (MAVSDK's form), 100 items in all.

``BENCH_MAVLINK_QUICK=1`` shortens the CPU windows and the repetitions (a loaded machine).

Run alone: ``.venv/bin/python -m bench mavlink``.
"""

from __future__ import annotations

import asyncio
import collections
import os
import socket
import sys
import tempfile
import time
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bench.bench_velocity import LEVELS, _platform_with_tap, _velocity_commands
from bench.serial_tap import Command
from bench.support import (
    _platform_log,
    cpu_seconds,
    percentiles,
    start_platform,
    stop_process,
)
from brasidas import security
from brasidas.netem.core import Profile
from platformd.sim.demo_area import offset

LAT, LON = 37.9415, 23.6530
QUICK = os.environ.get("BENCH_MAVLINK_QUICK") == "1"
CPU_S = 4.0 if QUICK else 10.0
ACKS = 50 if QUICK else 200
UPLOADS = 3 if QUICK else 5
CONNECTS = 3 if QUICK else 10
PARAM_FILE = b"@PARAM/param.pck?withdefaults=1"
MANUAL_SAMPLES = 200
ITEM_TIMEOUT = 0.5
"""The ground station's retry timer for a request it is waiting on (QGroundControl's is 1.5 s
for a whole transfer step; a shorter one only favours the client)."""


class BlockingGcs:
    """A ground station on a blocking UDP socket (run it in a thread)."""

    def __init__(self, sock: socket.socket, system: int = 255) -> None:
        self.sock = sock
        self.mav = mavlink.MAVLink(None, system, 190)
        self.parser = mavlink.MAVLink(None, 0, 0)
        self.parser.robust_parsing = True
        self.vehicle: tuple[str, int] | None = None

    def send(self, message: Any) -> None:
        assert self.vehicle is not None
        data = message.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        self.sock.sendto(data, self.vehicle)

    def receive(self, kinds: tuple[str, ...], deadline: float) -> Any | None:
        """The next message of one of ``kinds`` before ``deadline`` (perf_counter), or None."""
        while (left := deadline - time.perf_counter()) > 0:
            self.sock.settimeout(left)
            try:
                data, address = self.sock.recvfrom(4096)
            except TimeoutError:
                return None
            self.vehicle = address
            for message in self.parser.parse_buffer(data) or []:
                if message.get_type() in kinds:
                    return message
        return None

    def wait_vehicle(self, timeout: float = 30.0) -> None:
        if self.receive(("HEARTBEAT",), time.perf_counter() + timeout) is None:
            raise RuntimeError("no HEARTBEAT from the vehicle")
        self.heartbeat()

    def heartbeat(self) -> None:
        self.send(
            mavlink.MAVLink_heartbeat_message(
                mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3
            )
        )

    def command_rtt(self, count: int) -> list[float]:
        samples = []
        for _ in range(count):
            sent = time.perf_counter()
            self.send(
                mavlink.MAVLink_command_long_message(
                    1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 4, 0, 0, 0, 0, 0
                )
            )
            ack = self.receive(("COMMAND_ACK",), sent + 2.0)
            if ack is not None:
                samples.append((time.perf_counter() - sent) * 1000)
        return samples

    def qgc_connect(self) -> float:
        """QGroundControl's connect to "parameters complete" (its order; each step waits
        for its answer): seconds."""
        start = time.perf_counter()
        for message_id in (mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 300):  # 300: PROTOCOL_VERSION
            self.send(
                mavlink.MAVLink_command_long_message(
                    1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, message_id, 0, 0, 0, 0, 0, 0
                )
            )
            if self.receive(("COMMAND_ACK",), time.perf_counter() + 1.2) is None:
                raise RuntimeError(f"REQUEST_MESSAGE({message_id}) unanswered")
        request = bytearray(251)
        request[3], request[4] = 4, len(PARAM_FILE)  # OpenFileRO
        request[12 : 12 + len(PARAM_FILE)] = PARAM_FILE
        self.send(mavlink.MAVLink_file_transfer_protocol_message(0, 1, 1, list(request)))
        nak = self.receive(("FILE_TRANSFER_PROTOCOL",), time.perf_counter() + 1.0)
        if nak is None or bytes(nak.payload)[12] != 10:
            raise RuntimeError("MAVFTP: no FileNotFound NAK (QGroundControl would wait)")
        self.send(mavlink.MAVLink_param_request_list_message(1, 1))
        seen: set[int] = set()
        total = None
        while total is None or len(seen) < total:
            value = self.receive(("PARAM_VALUE",), time.perf_counter() + 5.0)
            if value is None:
                raise RuntimeError("parameters incomplete")
            total = value.param_count
            seen.add(value.param_index)
        return time.perf_counter() - start

    def upload(self, items: list[Any]) -> tuple[float, int]:
        """Seconds from MISSION_COUNT to MISSION_ACK ACCEPTED, and the resends it took."""
        start = time.perf_counter()
        count = mavlink.MAVLink_mission_count_message(1, 1, len(items), 0)
        self.send(count)
        last: Any = count
        resends = 0
        while time.perf_counter() - start < 60:
            message = self.receive(
                ("MISSION_REQUEST_INT", "MISSION_REQUEST", "MISSION_ACK"),
                time.perf_counter() + ITEM_TIMEOUT,
            )
            if message is None:
                self.send(last)  # the vehicle's answer or our message was lost
                resends += 1
                continue
            if message.get_type() == "MISSION_ACK":
                if message.type != mavlink.MAV_MISSION_ACCEPTED:
                    raise RuntimeError(f"upload refused: {message.type}")
                return time.perf_counter() - start, resends
            last = items[message.seq]
            self.send(last)
        raise RuntimeError("upload never finished")


def mission(count: int) -> list[Any]:
    """``count`` items: home (the global frame), then waypoints zigzagging inside the demo
    field, clear of the shed, each followed by a DO_CHANGE_SPEED (as MAVSDK sends speeds)."""
    items = [_item(0, LAT, LON, frame=0)]
    for seq in range(1, count):
        if seq % 2 == 0:
            items.append(
                mavlink.MAVLink_mission_item_int_message(
                    1, 1, seq, 2, 178, 0, 1, 1, 0.5 + (seq % 7) * 0.1, -1, 0, 0, 0, 0, 0
                )
            )
            continue
        east = -4 + (seq % 10) * 4.5
        north = 0 if (seq // 10) % 2 else 30
        lat, lon = offset(LAT, LON, east, north)
        items.append(_item(seq, lat, lon))
    return items


def _item(seq: int, lat: float, lon: float, frame: int = 3) -> Any:
    return mavlink.MAVLink_mission_item_int_message(
        1, 1, seq, frame, 16, 0, 1, 0, 0, 0, 0, round(lat * 1e7), round(lon * 1e7), 0, 0
    )


def _address(sock: socket.socket) -> str:
    host, port = sock.getsockname()[:2]
    return f"{host}:{port}"


def _loopback_socket() -> socket.socket:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    return sock


def _platform_overrides(state: str, target: str, *extra: str) -> list[str]:
    return [
        "navcam.enabled=false",
        "audio.enabled=false",
        "beacon.enabled=false",
        f"map.file={state}/map.geojson",
        f"autonomy.route_file={state}/route.json",
        f'mavlink.targets=["{target}"]',
        "mavlink.allow_unsigned_control=true",
        *extra,
    ]


async def _cpu(state: str) -> dict[str, Any]:
    figures: dict[str, Any] = {}
    for enabled in (False, True):
        with _loopback_socket() as sock:
            process = await start_platform(
                *_platform_overrides(
                    state, _address(sock), f"mavlink.enabled={str(enabled).lower()}"
                )
            )
            try:
                gcs = BlockingGcs(sock)
                if enabled:
                    await asyncio.to_thread(gcs.wait_vehicle)
                else:
                    await asyncio.sleep(3)  # started
                before, started = cpu_seconds(process.pid), time.monotonic()
                if enabled:
                    await asyncio.to_thread(_listen, gcs, CPU_S)
                else:
                    await asyncio.sleep(CPU_S)
                used = cpu_seconds(process.pid) - before
                figures[f"platform_cpu_percent_{'gcs' if enabled else 'no_mavlink'}"] = round(
                    100 * used / (time.monotonic() - started), 2
                )
            finally:
                await stop_process(process)
    figures["platform_cpu_percent_difference"] = round(
        figures["platform_cpu_percent_gcs"] - figures["platform_cpu_percent_no_mavlink"], 2
    )
    return figures


def _listen(gcs: BlockingGcs, seconds: float) -> int:
    """Receive telemetry for ``seconds``, heartbeating at 1 Hz; the messages received."""
    received = 0
    end = time.perf_counter() + seconds
    next_beat = time.perf_counter()
    while (now := time.perf_counter()) < end:
        if now >= next_beat:
            gcs.heartbeat()
            next_beat += 1.0
        if gcs.receive(("HEARTBEAT", "GLOBAL_POSITION_INT", "SYS_STATUS"), min(end, next_beat)):
            received += 1
    return received


async def _endpoint_cpu(state: str) -> dict[str, Any]:
    """The endpoint's own CPU in an in-process --sim platform: thread CPU time spent in its
    datagram handler, its ticks (telemetry) and its sends, over wall time, with one ground
    station heartbeating and receiving the default rates."""
    from brasidas.config import PlatformConfig, load_config
    from platformd.app import PlatformDaemon

    with _loopback_socket() as sock:
        config = load_config(
            PlatformConfig,
            None,
            [
                "signaling.port=0",
                "velocity.port=0",
                "sim.enabled=true",
                *_platform_overrides(state, _address(sock), "mavlink.enabled=true"),
            ],
        )
        daemon = PlatformDaemon(config, None)
        await daemon.start()
        try:
            service = next(a for a in daemon.supervisor.actors if a.name == "mavlink")
            spent = [0.0]

            def timed(function: Any) -> Any:
                def wrapper(*args: Any) -> Any:
                    started = time.thread_time()
                    try:
                        return function(*args)
                    finally:
                        spent[0] += time.thread_time() - started

                return wrapper

            vehicle = service.vehicle  # type: ignore[attr-defined]
            vehicle.tick = timed(vehicle.tick)
            service.datagram_received = timed(service.datagram_received)  # type: ignore[attr-defined]
            service._flush = timed(service._flush)  # type: ignore[attr-defined]
            gcs = BlockingGcs(sock)
            await asyncio.to_thread(gcs.wait_vehicle)
            spent[0] = 0.0
            started = time.monotonic()
            received = await asyncio.to_thread(_listen, gcs, CPU_S)
            wall = time.monotonic() - started
        finally:
            await daemon.stop()
    return {
        "gcs_cpu_percent": round(100 * spent[0] / wall, 3),
        "gcs_messages_per_s": round(received / wall, 1),
    }


async def _loopback(state: str) -> dict[str, Any]:
    with _loopback_socket() as sock:
        process = await start_platform(
            *_platform_overrides(state, _address(sock), "mavlink.enabled=true")
        )
        try:
            gcs = BlockingGcs(sock)
            await asyncio.to_thread(gcs.wait_vehicle)
            connects = [await asyncio.to_thread(gcs.qgc_connect) for _ in range(CONNECTS)]
            acks = await asyncio.to_thread(gcs.command_rtt, ACKS)
            uploads = [await asyncio.to_thread(gcs.upload, mission(100)) for _ in range(UPLOADS)]
        finally:
            await stop_process(process)
    figures: dict[str, Any] = {}
    connect = sorted(connects)
    figures["qgc_connect_to_params_median_s"] = round(connect[len(connect) // 2], 3)
    figures["qgc_connect_to_params_max_s"] = round(connect[-1], 3)
    ack = percentiles(acks)
    figures["command_ack_p50_ms"], figures["command_ack_p99_ms"] = ack["p50"], ack["p99"]
    figures["command_ack_lost"] = ACKS - len(acks)
    seconds = sorted(s for s, _ in uploads)
    figures["upload_100_loopback_median_s"] = round(seconds[len(seconds) // 2], 3)
    figures["upload_100_loopback_max_s"] = round(seconds[-1], 3)
    return figures


async def _lossy(state: str) -> dict[str, Any]:
    """Across the link emulator: the platform in one namespace, the ground station in another."""
    from brasidas.netem.netns import TestNetwork, socket_in, unavailable_reason

    reason = unavailable_reason()
    if reason is not None:
        return {"upload_100_lossy_skipped": reason}
    profile = Profile(loss=0.10, delay=0.050, jitter=0.020)
    with TestNetwork("mav") as network:
        station = network.add_host("gcs")
        rover = network.add_host("rover", impaired=True)
        network.impair("rover", down=profile, up=profile)
        sock = socket_in(station.namespace, socket.AF_INET, socket.SOCK_DGRAM)
        with sock:
            sock.bind((station.address, 14550))
            args = [sys.executable, "-m", "platformd", "--sim", "--insecure"]
            overrides = [
                *_platform_overrides(state, f"{station.address}:14550", "mavlink.enabled=true"),
                "mavlink.host=0.0.0.0",
                # A closed test namespace: unsigned control off loopback is what is measured.
                "mavlink.unsigned_control_off_loopback_i_accept_the_risk=true",
                "signaling.port=0",
                "velocity.port=0",
            ]
            for item in overrides:
                args += ["--set", item]
            env = {**os.environ, "XDG_STATE_HOME": state}
            with _platform_log() as log:
                rover.spawn(args, env=env, stderr=log)
            gcs = BlockingGcs(sock)
            await asyncio.to_thread(gcs.wait_vehicle, 60.0)
            results = [await asyncio.to_thread(gcs.upload, mission(100)) for _ in range(UPLOADS)]
    seconds = sorted(s for s, _ in results)
    return {
        "upload_100_lossy_median_s": round(seconds[len(seconds) // 2], 3),
        "upload_100_lossy_max_s": round(seconds[-1], 3),
        "upload_100_lossy_resends_median": sorted(r for _, r in results)[len(results) // 2],
        "lossy_profile": profile.describe(),
    }


async def _manual_control_to_serial() -> dict[str, Any]:
    """MANUAL_CONTROL at 20 Hz to the first byte of the changed AX3500 command."""
    key = security.load_or_create_key(security.default_key_path())
    figures: dict[str, Any] = {}
    with _loopback_socket() as sock:
        daemon, tap, simulator = await _platform_with_tap(
            key,
            "mavlink.enabled=true",
            f'mavlink.targets=["127.0.0.1:{sock.getsockname()[1]}"]',
            "mavlink.allow_unsigned_control=true",
            # MANUAL_CONTROL carries no send time: the speed cap assumes the worst latency
            # and clamps the higher levels to one value; without it each level is its own
            # serial command, so each message is matched to its byte.
            "safety.worst_latency_ms=0",
        )
        try:
            gcs = BlockingGcs(sock)
            await asyncio.to_thread(gcs.wait_vehicle)
            samples = await asyncio.to_thread(_drive, gcs, tap)
        finally:
            await daemon.stop()
            tap.close()
            simulator.close()
    result = percentiles(samples[5:])
    figures["manual_control_to_serial_p50_ms"] = result["p50"]
    figures["manual_control_to_serial_p99_ms"] = result["p99"]
    figures["manual_control_to_serial_matched"] = len(samples)
    return figures


def _drive(gcs: BlockingGcs, tap: Any) -> list[float]:
    ack_deadline = time.perf_counter() + 5
    gcs.send(
        mavlink.MAVLink_command_long_message(
            1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 0, 0, 0, 0, 0, 0
        )
    )
    ack = gcs.receive(("COMMAND_ACK",), ack_deadline)
    if ack is None or ack.result != mavlink.MAV_RESULT_ACCEPTED:
        raise RuntimeError("MANUAL refused")
    already = len(_velocity_commands(tap))
    sent_at: dict[int, float] = {}
    values: dict[int, float] = {}
    period = 0.05
    deadline = time.perf_counter()
    for number in range(MANUAL_SAMPLES):
        deadline += period
        while (left := deadline - time.perf_counter()) > 0:
            time.sleep(min(left, 0.0005) if left > 0.001 else 0)
        level = LEVELS[number % len(LEVELS)]
        values[number] = level
        sent_at[number] = time.perf_counter()
        gcs.send(mavlink.MAVLink_manual_control_message(1, round(level * 1000), 0, 500, 0, 0))
        if number % 20 == 0:
            gcs.heartbeat()
    time.sleep(0.2)
    written = _velocity_commands(tap)[already:]
    return _match_by_value(sent_at, values, written)


def _match_by_value(
    sent_at: dict[int, float], values: dict[int, float], written: list[Command]
) -> list[float]:
    """Each message's latency to the first command carrying its level's text after it (and
    before the same level comes round again). The level's text is the one most often first
    after it: a message the driver coalesced under load (latest wins) shifts nothing."""
    votes: dict[float, collections.Counter[str]] = collections.defaultdict(collections.Counter)
    order = sorted(sent_at)
    cursor = 0
    for number in order:
        while cursor < len(written) and written[cursor].first_byte_at < sent_at[number]:
            cursor += 1
        if cursor < len(written):
            votes[values[number]][written[cursor].text] += 1
    text = {level: counter.most_common(1)[0][0] for level, counter in votes.items()}
    samples: list[float] = []
    cursor = 0
    for index, number in enumerate(order):
        while cursor < len(written) and written[cursor].first_byte_at < sent_at[number]:
            cursor += 1
        horizon = order[index + len(LEVELS)] if index + len(LEVELS) < len(order) else None
        for command in written[cursor:]:
            if horizon is not None and command.first_byte_at >= sent_at[horizon]:
                break
            if command.text == text.get(values[number]):
                samples.append((command.first_byte_at - sent_at[number]) * 1000)
                break
    return samples


async def run() -> dict[str, Any]:
    figures: dict[str, Any] = {}
    with tempfile.TemporaryDirectory(prefix="bench-mavlink-") as state:
        figures.update(await _endpoint_cpu(state))
        figures.update(await _cpu(state))
        figures.update(await _loopback(state))
        figures.update(await _manual_control_to_serial())
        try:
            figures.update(await _lossy(state))
        except Exception as err:  # the namespaces need root: say why, keep the rest
            figures["upload_100_lossy_error"] = str(err)
    return figures
