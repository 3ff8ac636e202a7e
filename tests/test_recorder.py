"""The on-board recorder (issue 23): MCAP read back with the ``mcap`` reader, video decoded by
a stock GStreamer pipeline, a ``kill -9`` mid-recording, quotas and a full disk."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import logging
import os
import signal
import subprocess
import time
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from conftest import free_udp_port, quiet_platform_config, wait_until
from mcap.reader import NonSeekingReader, make_reader
from mcap.records import Message
from mcap.stream_reader import StreamReader
from support.cli import run_cli
from support.processes import sim_platform
from support.recorder import recorder_of
from support.velocity import open_connection, udp_socket

from brasidas import topics
from brasidas.annunciator import RECORDER_STOPPED, Annunciator
from brasidas.codecs import pvel
from brasidas.codecs.telemetry import MAX_DATAGRAM, TelemetryDecoder, TelemetryEncoder
from brasidas.codecs.telemetry_schema import (
    RecorderStatus,
    Snapshot,
    snapshot_from_wire,
    snapshot_to_wire,
)
from brasidas.config import TelemetryReceiverSection
from brasidas.media.gst import gst
from brasidas.messages import Velocity
from brasidas.recording import schemas
from brasidas.recording.writer import ACTIVE_SUFFIX, Quota, Recorder
from platformd.app import PlatformDaemon
from platformd.recorder import REASON_MAX_CHARS
from stationd.daemon import StationDaemon

Factory = Callable[..., Awaitable[PlatformDaemon]]
ROTATE_SECONDS = 9.0
"""The sim recording's files' length (recorder.rotate_minutes). Not shorter: on a starved CPU
the station's commands take seconds, the NavCam runs at its idle 5 fps until the override is
engaged, and a 5 s first file held 23 frames (30 asserted)."""


def read_messages(path: Path) -> dict[str, list[tuple[int, dict[str, Any]]]]:
    """Every message of a finished file by topic: (log time, decoded JSON)."""
    by_topic: dict[str, list[tuple[int, dict[str, Any]]]] = {}
    with open(path, "rb") as stream:
        for _schema, channel, message in make_reader(stream).iter_messages():
            by_topic.setdefault(channel.topic, []).append(
                (message.log_time, json.loads(message.data))
            )
    return by_topic


def summary_of(path: Path) -> Any:
    with open(path, "rb") as stream:
        return make_reader(stream).get_summary()


def messages_until_the_cut(path: Path) -> list[Message]:
    """The messages of a file cut short (no summary, maybe a half-written record at its end)."""
    messages: list[Message] = []
    with open(path, "rb") as stream:
        try:
            for record in StreamReader(stream).records:
                if isinstance(record, Message):
                    messages.append(record)
        except Exception:
            pass  # the cut: a record the kill interrupted
    return messages


def first_messages(directory: Path) -> list[bytes]:
    """The first message of every finished file, oldest file first."""
    firsts = []
    for path in sorted(directory.glob("*.mcap")):
        with open(path, "rb") as stream:
            _schema, _channel, first = next(iter(make_reader(stream).iter_messages()))
        firsts.append(first.data)
    return firsts


def finished_files(directory: Path) -> dict[str, int]:
    return {p.name: p.stat().st_size for p in sorted(directory.glob("*.mcap"))}


def decode_h264(path: Path) -> tuple[int, str]:
    """Frames a stock ``filesrc ! h264parse ! avdec_h264`` pipeline decodes, and its error."""
    Gst = gst()
    pipeline = Gst.parse_launch(
        f"filesrc location={path} ! h264parse ! avdec_h264 ! fakesink name=sink "
        "signal-handoffs=true sync=false"
    )
    frames = [0]
    pipeline.get_by_name("sink").connect("handoff", lambda *_: frames.__setitem__(0, frames[0] + 1))
    pipeline.set_state(Gst.State.PLAYING)
    message = pipeline.get_bus().timed_pop_filtered(
        60 * Gst.SECOND, Gst.MessageType.EOS | Gst.MessageType.ERROR
    )
    error = ""
    if message is None:
        error = "no end of stream in 60 s"
    elif message.type == Gst.MessageType.ERROR:
        error = message.parse_error()[0].message
    pipeline.set_state(Gst.State.NULL)
    return frames[0], error


async def test_a_sim_recording_is_listed_downloaded_and_reads_back(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    recordings = tmp_path / "recordings"
    platform = await platform_factory(
        quiet_platform_config(
            "platform.id=rover-23",
            "sim.enabled=true",
            "gps.enabled=true",
            "navcam.enabled=true",
            "motor.enabled=true",
            "recorder.enabled=true",
            f"recorder.dir={recordings}",
            f"recorder.rotate_minutes={ROTATE_SECONDS / 60}",
            f"map.file={tmp_path / 'map.geojson'}",
            f"autonomy.route_file={tmp_path / 'route.json'}",
        ),
        fleet_key,
    )
    code, _, _ = await run_cli(station, "connect", "rover-23", "--url", platform.ctx.signaling_url)
    assert code == 0
    port = str(free_udp_port())
    code, _, err = await run_cli(station, "stream", "rover-23", "navcam", "start", "--port", port)
    assert code == 0, err
    controller = topics.CONTROLLER_STATUS
    await wait_until(lambda: getattr(platform.bus.last(controller), "connected", False), 20)
    code, out, err = await run_cli(station, "lights", "rover-23", "main", "on")
    assert code == 0, out + err
    code, _, err = await run_cli(station, "movrd", "rover-23", "on")  # the motors to zero
    assert code == 0, err
    # The first file is finished when the writer rotates (rotate_minutes, at a keyframe).
    started = time.monotonic()
    while True:
        code, out, err = await run_cli(station, "logs", "rover-23", "--json")
        assert code == 0, err
        listing = json.loads(out)
        finished = [item for item in listing["recordings"] if not item["recording"]]
        if finished:
            break
        assert time.monotonic() - started < ROTATE_SECONDS + 30, listing
        await asyncio.sleep(0.5)
    assert listing["recording"] is True
    assert listing["counters"]["dropped"] == 0
    first = finished[0]
    # Rotated after its configured length, not early (a keyframe may end it a little later).
    assert first["duration_s"] > ROTATE_SECONDS - 2, first
    assert first["size"] > 10_000, first
    assert first["channels"]["/navcam"]["schema"] == "foxglove.CompressedVideo"
    code, out, _ = await run_cli(station, "logs", "rover-23")
    assert code == 0
    assert first["name"] in out
    assert "/navcam" in out

    target = tmp_path / "download.mcap"
    code, out, err = await run_cli(
        station, "logs", "rover-23", "get", first["name"], "-o", str(target)
    )
    assert code == 0, err
    original = (recordings / first["name"]).read_bytes()
    assert target.read_bytes() == original
    # Resumable: a cut download is completed from where it stopped (an HTTP range).
    target.write_bytes(original[: len(original) // 3])
    code, _, err = await run_cli(
        station, "logs", "rover-23", "get", first["name"], "-o", str(target)
    )
    assert code == 0, err
    assert target.read_bytes() == original

    # The file being written downloads as a complete MCAP (to its last closed chunk) that
    # the mcap package's seeking and streaming readers both open; a partial copy left by an
    # earlier download is replaced, not resumed.
    def being_written() -> Path | None:
        files = [p for p in recordings.glob(f"*{ACTIVE_SUFFIX}") if p.stat().st_size > 20_000]
        return files[0] if files else None

    await wait_until(lambda: being_written() is not None, 30)
    active = being_written()
    assert active is not None
    partial = tmp_path / "active.mcap"
    partial.write_bytes(b"stale bytes of an earlier copy")
    code, out, err = await run_cli(
        station, "logs", "rover-23", "get", active.name, "-o", str(partial)
    )
    assert code == 0, err
    live = await asyncio.to_thread(summary_of, partial)
    assert live is not None
    assert live.statistics is not None
    assert live.statistics.message_count > 0
    seeking = await asyncio.to_thread(read_messages, partial)
    assert seeking["/navcam"]
    assert seeking["/gps"]

    def streamed_count() -> int:
        with open(partial, "rb") as stream:
            return sum(1 for _ in NonSeekingReader(stream).iter_messages())

    assert await asyncio.to_thread(streamed_count) == live.statistics.message_count

    summary = await asyncio.to_thread(summary_of, target)
    assert summary is not None
    names = {
        channel.topic: summary.schemas[channel.schema_id].name
        for channel in summary.channels.values()
    }
    for topic, schema in {
        "/navcam": "foxglove.CompressedVideo",
        "/gps": "foxglove.LocationFix",
        "/pose": "foxglove.LocationFix",
        "/pose/local": "foxglove.PoseInFrame",
        "/log": "foxglove.Log",
        "/commands": "brasidas.Command",
        "/motor/command": "brasidas.Velocity",
        "/telemetry/gps": "brasidas.telemetry.Gps",
        "/telemetry/override": "brasidas.telemetry.Override",
    }.items():
        assert names.get(topic) == schema, (topic, names)

    messages = await asyncio.to_thread(read_messages, target)
    # Positions match telemetry: every GPS section recorded is a fix recorded before it.
    fixes = messages["/gps"]
    for when, section in messages["/telemetry/gps"]:
        if not section["fix"]:
            continue
        earlier = [fix for t, fix in fixes if t <= when]
        assert earlier, when
        assert any(
            abs(fix["latitude"] - section["lat"]) < 1e-6
            and abs(fix["longitude"] - section["lon"]) < 1e-6
            for fix in earlier[-3:]
        ), (section, earlier[-3:])
    # Who commanded what: the lights command, with the station that sent it.
    commands = [c for _t, c in messages["/commands"]]
    assert any(c["name"] == "10.6" and c["station"] and c["accepted"] for c in commands), commands
    assert any(c["name"] == "10.0" and c["payload"] == "True" for c in commands), commands
    assert messages["/motor/command"][-1][1] == {"linear": 0.0, "angular": 0.0}

    # The video: a keyframe first, Annex B access units that a stock decoder takes.
    video = [base64.b64decode(frame["data"]) for _t, frame in messages["/navcam"]]
    assert all(frame["format"] == "h264" for _t, frame in messages["/navcam"])
    assert len(video) >= 30
    assert video[0].startswith((b"\x00\x00\x00\x01", b"\x00\x00\x01"))
    assert b"\x00\x00\x01\x67" in video[0] or b"\x00\x00\x00\x01\x67" in video[0]  # SPS
    elementary = tmp_path / "navcam.h264"
    elementary.write_bytes(b"".join(video))
    frames, error = await asyncio.to_thread(decode_h264, elementary)
    assert not error, (frames, len(video), error)
    assert frames >= len(video) - 2, (frames, len(video), error)


async def test_kill_9_loses_at_most_the_open_chunk_and_the_next_start_recovers(
    platform_factory: Factory, tmp_path: Path
) -> None:
    recordings = tmp_path / "recordings"
    process, _port = await sim_platform(
        "beacon.enabled=false",
        "audio.enabled=false",
        f"recorder.dir={recordings}",
        "recorder.telemetry_hz=10",
        f"map.file={tmp_path / 'map.geojson'}",
        f"autonomy.route_file={tmp_path / 'route.json'}",
        stderr=asyncio.subprocess.DEVNULL,
    )
    try:
        await wait_until(lambda: any(recordings.glob(f"*{ACTIVE_SUFFIX}")), 60)
        (active,) = recordings.glob(f"*{ACTIVE_SUFFIX}")
        await wait_until(lambda: active.stat().st_size > 20_000, 60)
    finally:
        killed_at = time.time_ns()
        process.send_signal(signal.SIGKILL)
        await process.wait()

    # The file as the kill left it: every closed chunk reads back, the last one ~1 s old.
    messages = await asyncio.to_thread(messages_until_the_cut, active)
    assert messages
    lost_s = (killed_at - max(m.log_time for m in messages)) / 1e9
    assert lost_s < 2.0, f"{lost_s:.2f} s lost"  # chunk_seconds 1 (+ a loaded machine's lag)

    # The next start closes it: a finished file with the same messages.
    platform = await platform_factory(
        quiet_platform_config("recorder.enabled=true", f"recorder.dir={recordings}"),
        os.urandom(32),
    )
    recovered = active.with_name(active.name.removesuffix(ACTIVE_SUFFIX) + ".mcap")
    await wait_until(lambda: recovered.exists() and not active.exists(), 30)
    await wait_until(lambda: recorder_of(platform).writer.stats.recovered == 1)
    summary = await asyncio.to_thread(summary_of, recovered)
    assert summary is not None
    assert summary.statistics is not None
    assert summary.statistics.message_count == len(messages)


def _recorder(directory: Path, quota: Quota, **kwargs: Any) -> Recorder:
    return Recorder(
        directory,
        [schemas.COMMANDS, schemas.NAVCAM],
        prefix="test",
        quota=quota,
        video_channel=1,
        **kwargs,
    )


async def test_a_small_quota_rotates_and_deletes_the_oldest_first(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.INFO, "brasidas.recording.writer")
    recorder = _recorder(
        tmp_path,
        Quota(max_bytes=250_000, keep_days=30, min_free_bytes=0),
        rotate_seconds=0.2,
        chunk_seconds=0.05,
        check_seconds=0.05,
    )
    recorder.start()
    try:
        for _ in range(80):
            recorder.submit(0, time.time_ns(), os.urandom(20_000))  # incompressible
            await asyncio.sleep(0.02)
        await wait_until(lambda: recorder.stats.deleted >= 2, 10)
    finally:
        await asyncio.to_thread(recorder.stop)
    files = await asyncio.to_thread(finished_files, tmp_path)
    kept = sorted(files)
    deleted = sorted(
        r.getMessage().split()[2] for r in caplog.records if "(quota)" in r.getMessage()
    )
    assert kept
    assert len(deleted) == recorder.stats.deleted >= 2
    assert deleted[-1] < kept[0], (deleted, kept)  # the oldest went first
    assert sum(files.values()) <= 250_000 + 260_000
    assert recorder.stats.dropped == 0
    assert not recorder.stats.reason


async def test_video_waits_for_a_keyframe_in_every_file(tmp_path: Path) -> None:
    recorder = _recorder(tmp_path, Quota(10**9, 30, 0), rotate_seconds=0.3, chunk_seconds=0.05)
    recorder.start()
    try:
        for i in range(60):
            key = i % 10 == 3
            unit = b"\x00\x00\x00\x01" + (b"\x65KEY" if key else b"\x41DELTA")
            recorder.submit(1, time.time_ns(), unit, keyframe=key)
            await asyncio.sleep(0.02)
    finally:
        await asyncio.to_thread(recorder.stop)
    firsts = await asyncio.to_thread(first_messages, tmp_path)
    assert len(firsts) >= 2
    assert all(first.endswith(b"KEY") for first in firsts), firsts
    assert recorder.stats.waiting_keyframe >= 3  # the deltas before the first keyframe


async def test_a_full_disk_stops_recording_with_a_warning_and_teleop_carries_on(
    station: StationDaemon,
    platform_factory: Factory,
    fleet_key: bytes,
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.WARNING, "brasidas.recording.writer")
    # The floor above the disk's size: the disk is full as far as the recorder knows.
    daemon = await platform_factory(
        quiet_platform_config(
            "platform.id=rover-floor",
            "recorder.enabled=true",
            f"recorder.dir={tmp_path / 'recordings'}",
            f"recorder.min_free_bytes={2**50}",
        ),
        fleet_key,
    )
    recorder = recorder_of(daemon)
    await wait_until(lambda: bool(recorder.writer.stats.reason), 10)
    assert "disk full" in recorder.writer.stats.reason
    assert "recorder stopped: disk full" in caplog.text
    motors: list[Velocity] = []
    daemon.bus.subscribe(topics.MOTOR_COMMAND, motors.append)
    conn = await open_connection(daemon, fleet_key)
    sock = udp_socket()
    try:
        info = await conn.call("get_velocity_connection_info")
        encoder = pvel.PvelEncoder(key=conn.session_key, session_id=conn.session_id)
        assert await conn.call("set_manual_override", engaged=True) is True
        sock.sendto(encoder.encode(0.4, 0.1), (info["host"], info["port"]))
        await wait_until(lambda: bool(motors) and motors[-1] == Velocity(0.4, 0.1))
        listing = await conn.call("list_recordings")
        assert listing["recording"] is False
        assert "disk full" in listing["reason"]
        assert listing["counters"]["not_recording"] > 0
        await station_sees_the_recorder_stopped(station, daemon, "disk full", "DISK FULL")
    finally:
        sock.close()
        await conn.close()


async def test_a_quota_below_the_current_size_stops_deletes_the_oldest_and_resumes(
    tmp_path: Path,
) -> None:
    """The file being written outgrows the quota: recording stops with a warning (the file
    finished), the oldest files go (here that one: nothing can keep a file over the quota),
    and recording resumes in a new file."""
    events: list[tuple[int, str]] = []
    recorder = _recorder(
        tmp_path,
        Quota(max_bytes=60_000, keep_days=30, min_free_bytes=0),
        rotate_seconds=600,
        chunk_seconds=0.05,
        check_seconds=0.05,
        on_event=lambda level, text: events.append((level, text)),
    )
    recorder.start()
    try:
        for _ in range(10):
            recorder.submit(0, time.time_ns(), os.urandom(20_000))
            await asyncio.sleep(0.03)
        await wait_until(lambda: any("resumed" in text for _level, text in events), 10)
        assert recorder.stats.deleted >= 1
        recorder.submit(0, time.time_ns(), b'{"after": true}')
        await wait_until(lambda: recorder.stats.files >= 2, 10)
    finally:
        await asyncio.to_thread(recorder.stop)
    level, text = events[0]
    assert level == schemas.LOG_WARNING
    assert text.startswith("recording stopped: quota reached")
    assert events[1] == (schemas.LOG_INFO, "recording resumed")


async def test_downloads_need_a_session_and_a_plain_recording_name(
    platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    import aiohttp

    recordings = tmp_path / "recordings"
    daemon = await platform_factory(
        quiet_platform_config("recorder.enabled=true", f"recorder.dir={recordings}"), fleet_key
    )
    recorder = recorder_of(daemon)
    await wait_until(lambda: bool(recorder.writer.stats.current), 10)
    (tmp_path / "secret.mcap").write_bytes(b"not yours")
    conn = await open_connection(daemon, fleet_key)
    url = f"{daemon.ctx.signaling_url}/recordings"
    name = recorder.writer.stats.current
    try:
        async with aiohttp.ClientSession() as http:
            async with http.get(f"{url}/{name}") as response:
                assert response.status == 401  # no session
            async with http.get(
                f"{url}/{name}", headers={"X-Brasidas-Session": "forged"}
            ) as response:
                assert response.status == 401
            good = {"X-Brasidas-Session": conn.session_id}
            for bad in (
                "..%2Fsecret.mcap",
                "%2E%2E/secret.mcap",
                ".hidden.mcap",
                "x.txt",
                "a" * 300,
            ):
                async with http.get(f"{url}/{bad}", headers=good) as response:
                    assert response.status == 404, bad
            async with http.get(f"{url}/{name}", headers=good) as response:
                assert response.status == 200
                assert (await response.read()).startswith(b"\x89MCAP0\r\n")
            async with http.get(
                f"{url}/{name}", headers={**good, "Range": "bytes=0-7"}
            ) as response:
                assert response.status == 206
                assert await response.read() == b"\x89MCAP0\r\n"
    finally:
        await conn.close()


async def test_the_open_files_index_is_freed_at_every_rotation(tmp_path: Path) -> None:
    """The MCAP writer keeps a chunk's index entry until the file ends (the summary needs it):
    it grows a second at a time within a file and is freed at each rotation, never across."""
    import tracemalloc

    recorder = _recorder(
        tmp_path, Quota(10**9, 30, 0), rotate_seconds=0.4, chunk_seconds=0.02, check_seconds=60
    )

    def index_bytes() -> int:
        snapshot = tracemalloc.take_snapshot().filter_traces(
            [tracemalloc.Filter(True, "*mcap/writer.py")]
        )
        return sum(stat.size for stat in snapshot.statistics("filename"))

    tracemalloc.start()
    sizes: dict[int, int] = {}
    try:
        recorder.start()
        while len(sizes) < 2:
            recorder.submit(0, time.time_ns(), b'{"name": "10.6"}')
            files = recorder.stats.files
            if files in (3, 8) and files not in sizes and recorder.stats.written:
                sizes[files] = index_bytes()  # just after a rotation, both times
            await asyncio.sleep(0.002)
    finally:
        await asyncio.to_thread(recorder.stop)
        tracemalloc.stop()
    assert sizes[8] - sizes[3] < 4_000, sizes


@contextlib.contextmanager
def tiny_tmpfs(path: Path, size: str) -> Iterator[Path]:
    """A tmpfs of ``size`` mounted at ``path`` (root: the tests run as root, see docs/development.md)."""
    path.mkdir()
    mounted = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
        capture_output=True,
        text=True,
        check=False,
    )
    if mounted.returncode != 0:
        # The tests run as root, as CI does: a full disk is a real one here.
        pytest.fail(f"cannot mount a tmpfs: {mounted.stderr.strip()}")
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], check=False)


async def test_a_full_tmpfs_stops_recording_with_a_warning_and_teleop_carries_on(
    station: StationDaemon,
    platform_factory: Factory,
    fleet_key: bytes,
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.WARNING, "brasidas.recording.writer")
    with tiny_tmpfs(tmp_path / "disk", "120k") as disk:  # full within seconds at 30 fps
        daemon = await platform_factory(
            quiet_platform_config(
                "platform.id=rover-full",
                "sim.enabled=true",
                "navcam.enabled=true",
                "recorder.enabled=true",
                f"recorder.dir={disk}",
                "recorder.min_free_bytes=0",  # the disk itself says no: ENOSPC
                "recorder.chunk_seconds=0.2",
            ),
            fleet_key,
        )
        recorder = recorder_of(daemon)
        motors: list[Velocity] = []
        daemon.bus.subscribe(topics.MOTOR_COMMAND, motors.append)
        conn = await open_connection(daemon, fleet_key)
        sock = udp_socket()
        try:
            await conn.call("start_stream", name="navcam", port=free_udp_port())
            assert await conn.call("set_manual_override", engaged=True) is True  # 30 fps
            await wait_until(lambda: "write failed" in recorder.writer.stats.reason, 60)
            assert "No space left on device" in recorder.writer.stats.reason
            assert "recorder stopped: write failed" in caplog.text
            # The control path never noticed: the stream drives the motors.
            info = await conn.call("get_velocity_connection_info")
            encoder = pvel.PvelEncoder(key=conn.session_key, session_id=conn.session_id)
            sock.sendto(encoder.encode(0.4, 0.1), (info["host"], info["port"]))
            await wait_until(lambda: bool(motors) and motors[-1] == Velocity(0.4, 0.1))
            listing = await conn.call("list_recordings")
            assert listing["recording"] is False
            assert "write failed" in listing["reason"]
            assert (await conn.call("get_nav_camera_parameters"))["state"] == "playing"
            # The operator sees it: a station warning (90.23) in status and the notifications
            # the console shows, from the recorder's telemetry section.
            await station_sees_the_recorder_stopped(
                station, daemon, "No space left on device", "WRITE FAILED"
            )
        finally:
            sock.close()
            await conn.close()
            await daemon.stop()


async def station_sees_the_recorder_stopped(
    station: StationDaemon, daemon: PlatformDaemon, why: str, shown: str
) -> None:
    platform_id = daemon.ctx.config.platform.id
    code, _, err = await run_cli(station, "connect", platform_id, "--url", daemon.ctx.signaling_url)
    assert code == 0, err

    async def warned() -> list[dict[str, Any]]:
        while True:
            notes = await station.ctx.api.call_local("telemetry_notifications", limit=50)
            if any(n["code"] == str(RECORDER_STOPPED) and n["active"] for n in notes):
                return list(notes)
            await asyncio.sleep(0.05)

    notes = await asyncio.wait_for(warned(), 20)
    (note,) = [n for n in notes if n["code"] == str(RECORDER_STOPPED)]
    assert note["platform_id"] == platform_id, note
    assert why in note["message"], note
    code, out, err = await run_cli(station, "status", platform_id)
    assert code == 0, err
    assert f"RECORDER STOPPED: {shown}" in out, out
    assert f"recorder   STOPPED: {shown.lower()}" in out, out
    assert "not recorded" in out, out
    code, out, _ = await run_cli(station, "status", platform_id, "--json")
    section = json.loads(out)["telemetry"]["snapshot"]["recorder"]
    assert section["recording"] is False
    assert why in section["reason"]
    assert section["not_recorded"] > 0


def test_a_stopped_recorder_is_a_station_warning_until_it_records_again() -> None:
    annunciator = Annunciator(TelemetryReceiverSection())
    assert annunciator.evaluate(Snapshot({RecorderStatus: RecorderStatus(True)}), 0, None, 1) == []
    idle = RecorderStatus(False)  # nothing to record yet: no warning
    assert annunciator.evaluate(Snapshot({RecorderStatus: idle}), 0, None, 2) == []
    stopped = RecorderStatus(False, "quota reached: 2.0 GiB of 2.0 GiB", 0, 12)
    (change,) = annunciator.evaluate(Snapshot({RecorderStatus: stopped}), 0, None, 3)
    assert change.active
    assert change.warning.code == RECORDER_STOPPED
    assert change.warning.message == "recorder stopped: quota reached: 2.0 GiB of 2.0 GiB"
    (change,) = annunciator.evaluate(Snapshot({RecorderStatus: RecorderStatus(True)}), 0, None, 4)
    assert not change.active
    assert change.warning.code == RECORDER_STOPPED


def test_a_stopped_recorder_with_its_longest_reason_reaches_the_station_whole() -> None:
    """On top of the fullest snapshot it may take a datagram of its own (the encoder splits by
    section): every datagram stays under the limit and the station gets the section entire."""
    from test_telemetry_schema import FULL

    longest = RecorderStatus(False, "x" * REASON_MAX_CHARS, 2**31, 2**31)
    encoder = TelemetryEncoder("brasidas-1", bytes(32))
    decoder = TelemetryDecoder("brasidas-1", bytes(32))
    sections: dict[str, Any] = {}
    for datagram in encoder.encode(snapshot_to_wire({**FULL, RecorderStatus: longest}), 0.0):
        assert len(datagram) < MAX_DATAGRAM
        sections.update(decoder.decode(datagram).sections)
    decoded, unknown = snapshot_from_wire(sections)
    assert unknown == []
    assert decoded.get(RecorderStatus) == longest
