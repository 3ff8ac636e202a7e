"""A hostile mesh, second round (issue 26): the rows of ``make bench hostile`` that run on
loopback (no namespaces needed), after round one's.

- **Replay**: a signed ground station drives a ``--sim`` platform (MANUAL, the joystick,
  HOLD); its datagrams, recorded, are sent again from a new source port 1 s later,
  ``BENCH_HOSTILE_REPLAY_WAIT_S`` (60) s later, and after the platform restarts: the commands
  accepted (COMMAND_ACK ACCEPTED to the replayer).
- **Spoofed video**: an unsigned REQUEST_MESSAGE(VIDEO_STREAM_INFORMATION) every second for
  ``BENCH_HOSTILE_VIDEO_S`` (21) s from a stranger's address: the bytes that address receives
  (MAVLink answers and RTP on the NavCam's port) over the bytes it sent.
- **Big files**: a station holding the override drives at 20 Hz while it imports a
  150,001-vertex boundary and a 25,000-item ``.plan`` one after another for
  ``BENCH_HOSTILE_IMPORT_S`` (5) s, while the operator's command (another
  process, through the station's local API as ``brasidas-station map``/``route`` sends it)
  imports the boundary, the plan and a 172,000-coordinate KML ``BENCH_HOSTILE_REPEATS`` (3)
  times each, while another session (another process) sends the boundary straight to the
  platform's ``load_map`` as many times, and while 16 downloads of a recording run: the time to the answer, the
  platform's and the station's RSS growth (the station runs in this process: the files' texts
  are made before), a probe's heartbeat p99, how late the station's loop wakes and the
  deadman stops meanwhile.

Only these rows: ``BENCH_HOSTILE_ONLY=round2 python -m bench hostile``.
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import json
import math
import os
import shutil
import socket
import sys
import tempfile
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from bench.support import (
    PLATFORM_LOG,
    connect_to_platform,
    free_port,
    percentiles,
    rss_mb,
    start_platform,
    station_connect,
    stop_process,
)
from brasidas import security
from brasidas.codecs.jsonrpc import RpcError
from brasidas.config import StationConfig, load_config
from stationd.client import PlatformConnection
from stationd.daemon import StationDaemon

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "tests"))
from mavlink_gcs import Gcs

PASSPHRASE = "bench hostile round two"
REPLAY_WAIT_S = float(os.environ.get("BENCH_HOSTILE_REPLAY_WAIT_S", "60"))
VIDEO_S = float(os.environ.get("BENCH_HOSTILE_VIDEO_S", "21"))
REPEATS = int(os.environ.get("BENCH_HOSTILE_REPEATS", "3"))
IMPORT_S = float(os.environ.get("BENCH_HOSTILE_IMPORT_S", "5"))
SETTLE_S = 2.0
"""After a replay or the last request, how long answers (and RTP) may still arrive."""


async def run() -> dict[str, Any]:
    figures: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as scratch:
        key_file = Path(scratch) / "mavlink.pass"
        key_file.write_text(PASSPHRASE + "\n")
        key_file.chmod(0o600)
        figures |= await _replay(key_file, Path(scratch))
        figures |= await _spoofed_video(key_file)
    figures |= await _big_files()
    figures["loadavg"] = list(os.getloadavg())
    return figures


# --------------------------------------------------------------------------- replay


@contextlib.asynccontextmanager
async def _mavlink_platform(*extra: str) -> AsyncIterator[tuple[asyncio.subprocess.Process, int]]:
    port = free_port(socket.SOCK_DGRAM)
    process = await start_platform("mavlink.enabled=true", f"mavlink.port={port}", *extra)
    try:
        yield process, port
    finally:
        await stop_process(process)


async def _replay(key_file: Path, scratch: Path) -> dict[str, Any]:
    gcs = await Gcs.open()
    state = f"mavlink.signing_state_file={scratch / 'signing.json'}"
    settings = (
        f'mavlink.targets=["127.0.0.1:{gcs.port}"]',
        f"mavlink.signing_key_file={key_file}",
        state,
    )
    figures: dict[str, Any] = {}
    try:
        async with _mavlink_platform(*settings) as (_, port):
            await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 1, timeout=60)
            gcs.sign(PASSPHRASE)
            capture = await _drive(gcs)
            figures["replay_capture_frames"] = len(capture)
            await asyncio.sleep(1.0)
            figures["replay_1s_accepted"] = await _send_again(capture, port)
            await asyncio.sleep(REPLAY_WAIT_S)
            figures[f"replay_{REPLAY_WAIT_S:g}s_accepted"] = await _send_again(capture, port)
        async with _mavlink_platform(*settings) as (_, port):
            await gcs.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 1, timeout=60)
            figures["replay_after_restart_accepted"] = await _send_again(capture, port)
    finally:
        gcs.close()
    return figures


async def _drive(gcs: Gcs) -> list[bytes]:
    """MANUAL, the joystick forward for a second, HOLD, as a ground station drives."""
    gcs.send(
        mavlink.MAVLink_heartbeat_message(
            mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0, 3
        )
    )
    ack = await gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 0)
    if ack.result != mavlink.MAV_RESULT_ACCEPTED:
        raise RuntimeError(f"the signed ground station was refused MANUAL ({ack.result})")
    for _ in range(20):
        gcs.send(mavlink.MAVLink_manual_control_message(1, 500, 0, 500, 0, 0))
        await asyncio.sleep(0.05)
    await gcs.command(mavlink.MAV_CMD_DO_SET_MODE, 1, 4)
    return list(gcs.frames)


async def _send_again(capture: list[bytes], port: int) -> int:
    """The capture from a new source port, at its pace; the commands it got ACCEPTED."""
    replayer = await Gcs.open()
    replayer.vehicle = ("127.0.0.1", port)
    try:
        for frame in capture:
            replayer.send_raw(frame)
            await asyncio.sleep(0.05)
        await asyncio.sleep(SETTLE_S)
        return sum(
            1
            for message in replayer.received
            if message.get_type() == "COMMAND_ACK" and message.result == mavlink.MAV_RESULT_ACCEPTED
        )
    finally:
        replayer.close()


# --------------------------------------------------------------------------- spoofed video


async def _spoofed_video(key_file: Path) -> dict[str, Any]:
    loop = asyncio.get_running_loop()
    victim_rtp = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    victim_rtp.bind(("127.0.0.1", 0))
    victim_rtp.setblocking(False)
    rtp_port = victim_rtp.getsockname()[1]
    received = [0]

    def drain() -> None:
        with contextlib.suppress(BlockingIOError):
            while True:
                received[0] += len(victim_rtp.recv(65536))

    loop.add_reader(victim_rtp.fileno(), drain)
    target = await Gcs.open()  # the configured ground station, elsewhere
    attacker = await Gcs.open(system=249)
    try:
        async with _mavlink_platform(
            f'mavlink.targets=["127.0.0.1:{target.port}"]',
            f"mavlink.signing_key_file={key_file}",
            "navcam.enabled=true",
            f"navcam.port={rtp_port}",
        ) as (_, port):
            await target.expect("HEARTBEAT", lambda m: m.get_srcComponent() == 1, timeout=60)
            attacker.vehicle = ("127.0.0.1", port)
            request = mavlink.MAVLink_command_long_message(
                1, 100, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                mavlink.MAVLINK_MSG_ID_VIDEO_STREAM_INFORMATION, 0, 0, 0, 0, 0, 0,
            )  # fmt: skip
            deadline = time.monotonic() + VIDEO_S
            while time.monotonic() < deadline:
                attacker.send(request)
                await asyncio.sleep(1.0)
            await asyncio.sleep(SETTLE_S)
    finally:
        loop.remove_reader(victim_rtp.fileno())
        victim_rtp.close()
        target.close()
        attacker.close()
    sent = sum(len(frame) for frame in attacker.frames)
    back = attacker.bytes_received + received[0]
    return {
        "spoofed_video_bytes_in": sent,
        "spoofed_video_bytes_out": back,
        "spoofed_video_rtp_bytes": received[0],
        "spoofed_video_ratio": round(back / sent, 3),
    }


# --------------------------------------------------------------------------- big files


def _boundary(vertices: int) -> dict[str, Any]:
    lat, lon = 37.9415, 23.6530
    ring = [
        [round(lon + 0.002 * math.cos(2 * math.pi * i / vertices), 6),
         round(lat + 0.002 * math.sin(2 * math.pi * i / vertices), 6)]
        for i in range(vertices)
    ]  # fmt: skip
    ring.append(ring[0])
    feature = {
        "type": "Feature",
        "properties": {"role": "boundary"},
        "geometry": {"type": "Polygon", "coordinates": [ring]},
    }
    return {"type": "FeatureCollection", "features": [feature]}


def _kml(coordinates: int) -> str:
    lat, lon = 37.9415, 23.6530
    tuples = " ".join(
        f"{lon + 0.002 * math.cos(2 * math.pi * i / coordinates):.6f},"
        f"{lat + 0.002 * math.sin(2 * math.pi * i / coordinates):.6f},0"
        for i in range(coordinates)
    )
    return (
        '<?xml version="1.0"?><kml xmlns="http://www.opengis.net/kml/2.2"><Document>'
        f"<Placemark><Polygon><outerBoundaryIs><LinearRing><coordinates>{tuples}</coordinates>"
        "</LinearRing></outerBoundaryIs></Polygon></Placemark></Document></kml>"
    )


def _plan(items: int) -> str:
    mission = [
        {"type": "SimpleItem", "command": 16, "frame": 3,
         "params": [0, 0, 0, None, 37.9415 + i * 1e-6, 23.6530, 0]}
        for i in range(items)
    ]  # fmt: skip
    plan = {
        "fileType": "Plan",
        "version": 1,
        "groundStation": "QGroundControl",
        "mission": {"version": 2, "items": mission, "plannedHomePosition": [37.9415, 23.653, 0]},
        "geoFence": {"version": 2, "polygons": [], "circles": []},
        "rallyPoints": {"version": 2, "points": []},
    }
    return json.dumps(plan, separators=(",", ":"))


async def _big_files() -> dict[str, Any]:
    signaling = free_port()
    process = await start_platform(f"signaling.port={signaling}")
    key = security.load_or_create_key(security.default_key_path())
    station = StationDaemon(load_config(StationConfig, None, ["station.api_port=0"]), key)
    boundary_text = json.dumps(_boundary(150_001), separators=(",", ":"))
    plan_text = _plan(25_000)
    kml_text = _kml(172_000)
    figures: dict[str, Any] = {
        "big_boundary_kib": len(boundary_text) // 1024,
        "big_plan_kib": len(plan_text) // 1024,
        "big_kml_kib": len(kml_text) // 1024,
    }
    scratch = Path(tempfile.mkdtemp(prefix="bench-hostile-"))
    files = {"big.geojson": boundary_text, "big.plan": plan_text, "big.kml": kml_text}
    for name, text in files.items():
        await asyncio.to_thread((scratch / name).write_text, text)
    try:
        await station.start()
        api = station.ctx.api
        await station_connect(api, f"http://127.0.0.1:{signaling}", timeout=60)
        answer = await api.call_local("movrd", platform_id="brasidas-1", engaged=True)
        if not answer.get("accepted"):
            raise RuntimeError(f"manual override refused: {answer}")
        probe = await connect_to_platform(signaling)
        async with asyncio.TaskGroup() as group:
            driving = group.create_task(_drive_station(api))
            try:
                await asyncio.sleep(SETTLE_S)
                # The same figures with nothing going on: what the machine's load alone costs.
                figures |= await _during("baseline", process.pid, probe, _idle(8.0))
                station_import = {
                    "boundary_150001": ("map_import", boundary_text, "big.geojson"),
                    "plan_25000": ("route_import", plan_text, "big.plan"),
                }
                for row, (method, text, name) in station_import.items():
                    figures |= await _during(
                        row, process.pid, probe, _import(api, method, text, name)
                    )
                # The operator's command, as it sends them (another process, the local API's
                # HTTP): the station reads the request too. Repeated: nothing may pile up.
                commands = {
                    "cli_boundary_150001": ("map_import", "big.geojson"),
                    "cli_plan_25000": ("route_import", "big.plan"),
                    "cli_kml_172000": ("map_import", "big.kml"),
                }
                for row, (method, name) in commands.items():
                    figures |= await _during(
                        row,
                        process.pid,
                        probe,
                        _commands(station.api_port, method, scratch / name, REPEATS),
                    )
                # Another session (not the probe's connection, whose messages would queue
                # behind it), from another process as another station would (its encoding
                # of the 3 MB map is not the driving station's), sends the boundary straight
                # to the platform.
                figures |= await _during(
                    "boundary_150001_direct",
                    process.pid,
                    probe,
                    _direct(signaling, scratch / "big.geojson", REPEATS),
                )
                figures |= await _during(
                    "downloads_16", process.pid, probe, _downloads(signaling, probe.session_id)
                )
            finally:
                driving.cancel()
        await probe.close()
    finally:
        await station.stop()
        await stop_process(process)
        await asyncio.to_thread(shutil.rmtree, scratch)
    return figures


async def _commands(api_port: int, method: str, path: Path, repeats: int) -> str:
    """``repeats`` imports of ``path`` by the operator's command's own client, in another
    process; the last answer."""
    script = (
        "import asyncio, sys\n"
        "from brasidas.codecs.jsonrpc import RpcError\n"
        "from brasidas.config import StationConfig, load_config\n"
        "from stationd.api_client import api_call_async\n"
        "config = load_config(StationConfig, None, [f'station.api_port={sys.argv[1]}'])\n"
        "text = open(sys.argv[3]).read()\n"
        "for _ in range(int(sys.argv[4])):\n"
        "    try:\n"
        "        asyncio.run(api_call_async(config, sys.argv[2], platform_id='brasidas-1',\n"
        "                                   text=text, filename=sys.argv[3]))\n"
        "        answer = 'accepted'\n"
        "    except RpcError as err:\n"
        "        answer = err.message\n"
        "print(answer)\n"
    )
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-c", script, str(api_port), method, str(path), str(repeats),
        stdout=asyncio.subprocess.PIPE,
    )  # fmt: skip
    out, _ = await process.communicate()
    return f"{repeats}x: {out.decode().strip()}"


async def _direct(signaling: int, path: Path, repeats: int) -> str:
    """``repeats`` ``load_map`` calls with the map in ``path`` from another session in
    another process; the last answer."""
    process = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "bench.hostile_round2", "load_map", str(signaling), str(path),
        str(repeats),
        stdout=asyncio.subprocess.PIPE,
    )  # fmt: skip
    out, _ = await process.communicate()
    return f"{repeats}x: {out.decode().strip()}"


async def _load_map_for(signaling: int, path: Path, repeats: int) -> str:
    """(The other session's process.) ``load_map`` with ``path``'s map, ``repeats`` times."""
    key = security.load_or_create_key(security.default_key_path())
    area = json.loads(path.read_text())  # noqa: ASYNC240 (its own process: nothing waits)
    other = PlatformConnection(
        "brasidas-1",
        f"http://127.0.0.1:{signaling}",
        station_id="bench-other",
        fleet_key=key,
        timeout=30.0,
    )
    await other.open()
    try:
        answer = ""
        for _ in range(repeats):
            answer = await _refused(other.call("load_map", map=area))
        return answer
    finally:
        await other.close()


DOWNLOAD_MB = 32
DOWNLOADERS = 16
DOWNLOAD_S = float(os.environ.get("BENCH_HOSTILE_DOWNLOAD_S", "10"))


async def _downloads(signaling: int, session: str) -> str:
    """16 parallel downloads of a 32 MB recording for ``BENCH_HOSTILE_DOWNLOAD_S`` (10) s, from
    another process (as another station would: not on the driving station's loop); one
    recording planted (the live one is small). What they got together."""
    folder = security.state_dir() / "recordings"
    name = "bench-hostile-download.mcap"
    await asyncio.to_thread(folder.mkdir, parents=True, exist_ok=True)
    await asyncio.to_thread((folder / name).write_bytes, os.urandom(DOWNLOAD_MB * 1024 * 1024))
    url = f"http://127.0.0.1:{signaling}/recordings/{name}"
    try:
        process = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "bench.hostile_round2", url, session,
            str(DOWNLOADERS), str(DOWNLOAD_S),
            stdout=asyncio.subprocess.PIPE,
        )  # fmt: skip
        out, _ = await process.communicate()
    finally:
        await asyncio.to_thread((folder / name).unlink, missing_ok=True)
    return out.decode().strip()


async def _download_for(url: str, session: str, count: int, seconds: float) -> str:
    """(The downloaders' process.) ``count`` parallel GETs of ``url`` for ``seconds``."""
    import aiohttp

    got = [0]

    async def one(http: aiohttp.ClientSession) -> None:
        async with http.get(url, headers={"X-Brasidas-Session": session}) as response:
            async for chunk in response.content.iter_chunked(65536):
                got[0] += len(chunk)

    started = time.monotonic()
    async with aiohttp.ClientSession() as http:
        tasks = [asyncio.ensure_future(one(http)) for _ in range(count)]
        _, pending = await asyncio.wait(tasks, timeout=seconds)
        for task in pending:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
    rate = got[0] / (time.monotonic() - started) / 1024
    return f"{count} downloads: {rate:.0f} KiB/s together"


async def _drive_station(api: Any) -> None:
    """The holder's setpoint every 50 ms (the station streams ``$PVEL`` at 20 Hz)."""
    while True:
        with contextlib.suppress(RpcError):
            await api.call_local("teleop_set", platform_id="brasidas-1", linear=0.3, angular=0.0)
        await asyncio.sleep(0.05)


async def _import(api: Any, method: str, text: str, name: str) -> str:
    """Imports one after another for ``BENCH_HOSTILE_IMPORT_S`` (5) s, at least ``REPEATS``
    (a p99 of the heartbeats needs some within them); how many, and the last answer."""
    answer = ""
    count = 0
    started = time.monotonic()
    while count < REPEATS or time.monotonic() - started < IMPORT_S:
        answer = await _refused(
            api.call_local(method, platform_id="brasidas-1", text=text, filename=name)
        )
        count += 1
    return f"{count}x: {answer}"


async def _idle(seconds: float) -> str:
    await asyncio.sleep(seconds)
    return "nothing sent"


async def _refused(call: Any) -> str:
    try:
        await call
    except RpcError as err:
        return err.message
    except (ConnectionError, TimeoutError) as err:  # the sender's own session lost meanwhile
        return f"{type(err).__name__}: {err}"
    return "accepted"


async def _during(row: str, pid: int, probe: Any, work: Any) -> dict[str, Any]:
    """``work``'s time to its answer, the platform's RSS growth, the probe's heartbeats and
    the deadman stops (the platform's log) meanwhile (and a second after)."""
    deadman_before = _deadman_lines()
    rss_before = rss_mb(pid)
    gc.collect()
    station_before = rss_mb(os.getpid())
    samples: list[float] = []
    lags: list[float] = []
    done = asyncio.Event()

    async def loop_lag() -> None:
        """How late this loop (the driving station's) wakes from 5 ms sleeps."""
        while not done.is_set():
            started = time.perf_counter()
            await asyncio.sleep(0.005)
            lags.append((time.perf_counter() - started - 0.005) * 1000)

    async def heartbeats() -> None:
        while not done.is_set():
            started = time.perf_counter()
            await probe.call("heartbeat")
            samples.append((time.perf_counter() - started) * 1000)
            await asyncio.sleep(0.05)

    async with asyncio.TaskGroup() as group:
        beating = group.create_task(heartbeats())
        lagging = group.create_task(loop_lag())
        started = time.perf_counter()
        answer = await work
        seconds = time.perf_counter() - started
        await asyncio.sleep(1.0)
        done.set()
        await beating
        await lagging
    return {
        f"{row}_answer": answer[:100],
        f"{row}_refused_s": round(seconds, 3),
        f"{row}_platform_rss_growth_mb": round(rss_mb(pid) - rss_before, 1),
        f"{row}_station_rss_growth_mb": round(rss_mb(os.getpid()) - station_before, 1),
        f"{row}_heartbeat_ms": percentiles(samples),
        f"{row}_station_loop_lag_ms": percentiles(lags),
        f"{row}_deadman_stops": _deadman_lines() - deadman_before,
    }


def _deadman_lines() -> int:
    try:
        return PLATFORM_LOG.read_text(errors="replace").count("deadman:")
    except FileNotFoundError:
        return 0


if __name__ == "__main__":
    if sys.argv[1] == "load_map":
        print(asyncio.run(_load_map_for(int(sys.argv[2]), Path(sys.argv[3]), int(sys.argv[4]))))
    else:
        print(
            asyncio.run(
                _download_for(sys.argv[1], sys.argv[2], int(sys.argv[3]), float(sys.argv[4]))
            )
        )
