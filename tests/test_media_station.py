"""Station side of the media: daemon receivers, ``view``, the stock gst-launch receiver, SDP."""

from __future__ import annotations

import asyncio
import json
import re
import shlex
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest
from conftest import free_udp_port, quiet_platform_config, udp_port_bound, wait_until
from support.cli import run_cli

from brasidas.codecs.jsonrpc import RpcError
from platformd.app import PlatformDaemon
from stationd.daemon import StationDaemon
from stationd.media import GST_LAUNCH_RECEIVER, sdp_text

Factory = Callable[..., Awaitable[PlatformDaemon]]
DECODED_FRAME = re.compile(r"chain.*\(460800 bytes")
"""fakesink -v: one decoded 640x480 I420 frame."""


async def sim_platform(factory: Factory, key: bytes, *overrides: str) -> PlatformDaemon:
    return await factory(
        quiet_platform_config(
            "platform.id=rover-v", "sim.enabled=true", "navcam.enabled=true", *overrides
        ),
        key,
    )


async def read_until(process: asyncio.subprocess.Process, pattern: re.Pattern[str]) -> str:
    """Lines of the process's stdout until one matches; the match is returned."""
    assert process.stdout is not None
    while True:
        line = (await process.stdout.readline()).decode(errors="replace")
        if not line:
            raise AssertionError("process ended before producing the expected output")
        if pattern.search(line):
            return line


async def stop_process(process: asyncio.subprocess.Process) -> None:
    if process.returncode is None:
        process.terminate()
        try:
            await asyncio.wait_for(process.wait(), 5)
        except TimeoutError:
            process.kill()
            await process.wait()


async def test_daemon_receiver_reports_latency_and_stops_with_the_platform(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes
) -> None:
    platform = await sim_platform(platform_factory, fleet_key)
    await station.ctx.api.call_local(
        "connect", platform_id="rover-v", url=platform.ctx.signaling_url
    )
    started = await station.ctx.api.call_local("receive", platform_id="rover-v")
    assert started["state"] == "playing"

    async def stats() -> dict[str, object]:
        receivers = await station.ctx.api.call_local("receivers")
        return dict(receivers[0])

    await asyncio.wait_for(_until_latency(stats), 10)
    streams = await station.ctx.api.call_local("streams", platform_id="rover-v")
    assert streams[0]["state"] == "playing"
    assert streams[0]["host"] == "127.0.0.1"
    assert await station.ctx.api.call_local("stop_receive", platform_id="rover-v")
    nav = platform.ctx.media.nav_camera
    await wait_until(lambda: nav()["state"] == "idle")
    assert await station.ctx.api.call_local("receivers") == []


async def _until_latency(stats: Callable[[], Awaitable[dict[str, object]]]) -> None:
    while True:
        current = await stats()
        if current.get("latency_ms") is not None and int(str(current["frames"])) >= 3:
            return
        await asyncio.sleep(0.05)


async def test_view_command_receives_and_stops_the_stream(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes
) -> None:
    platform = await sim_platform(platform_factory, fleet_key)
    url = platform.ctx.signaling_url
    code, out, err = await run_cli(
        station, "view", "rover-v", "--url", url, "--sink", "fakesink", "--seconds", "2", "--json"
    )
    assert code == 0, err
    lines = out.strip().splitlines()
    assert "640x480" in lines[0]
    assert "H264" in lines[0]
    last = json.loads(lines[-1])
    assert last["frames"] > 0
    assert last["latency_ms"] is not None
    assert platform.ctx.media.nav_camera()["state"] == "idle"  # stopped on exit

    code, out, err = await run_cli(
        station, "view", "rover-v", "nosuchstream", "--url", url, "--sink", "fakesink"
    )
    assert code == 1
    assert "no stream named 'nosuchstream'" in err


async def test_view_without_a_display_says_so(
    station: StationDaemon, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    code, _, err = await run_cli(station, "view", "rover-v")
    assert code == 1
    assert "no display" in err
    assert "--sdp" in err


async def test_stock_gst_launch_receiver_decodes_the_navcam(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    """The documented command (Annex A style), with fakesink instead of a window."""
    port = free_udp_port()
    platform = await sim_platform(platform_factory, fleet_key, f"navcam.port={port}")
    command = GST_LAUNCH_RECEIVER.format(port=port).replace(
        "videoconvert ! autovideosink sync=false", "fakesink silent=false"
    )
    argv = [*shlex.split(command)]
    argv.insert(1, "-v")
    process = await asyncio.create_subprocess_exec(
        *argv, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.STDOUT
    )
    try:
        await wait_until(lambda: udp_port_bound(port), timeout=10)  # before the first keyframe
        service = platform.ctx.media
        await service.start_stream("navcam", "127.0.0.1")
        await asyncio.wait_for(read_until(process, DECODED_FRAME), 10)
    finally:
        await stop_process(process)


async def test_sdp_file_plays_in_a_stock_sdp_receiver(
    platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    port = free_udp_port()
    text = sdp_text(port, listen_host="127.0.0.1", platform_host="127.0.0.1")
    assert f"m=video {port} RTP/AVP 96" in text
    assert "a=rtpmap:96 H264/90000" in text
    sdp = tmp_path / "navcam.sdp"
    sdp.write_text(text)
    platform = await sim_platform(platform_factory, fleet_key, f"navcam.port={port}")
    # sdpdemux reads the file as ffplay and VLC do: address, port, payload type, codec.
    process = await asyncio.create_subprocess_exec(
        "gst-launch-1.0",
        "-v",
        "filesrc",
        f"location={sdp}",
        "!",
        "sdpdemux",
        "latency=0",
        "!",
        "rtph264depay",
        "!",
        "avdec_h264",
        "!",
        "fakesink",
        "silent=false",
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.STDOUT,
    )
    try:
        await wait_until(lambda: udp_port_bound(port), timeout=10)  # sdpdemux's udpsrc
        service = platform.ctx.media
        await service.start_stream("navcam", "127.0.0.1")
        await asyncio.wait_for(read_until(process, DECODED_FRAME), 10)
    finally:
        await stop_process(process)


async def test_station_hears_the_platform_and_talks_back(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes
) -> None:
    platform = await sim_platform(
        platform_factory, fleet_key, "audio.enabled=true", f"audio.in_port={free_udp_port()}"
    )
    api = station.ctx.api
    await api.call_local("connect", platform_id="rover-v", url=platform.ctx.signaling_url)
    heard = await api.call_local("receive", platform_id="rover-v", stream="audio_out")
    assert heard["state"] == "playing"
    assert heard["codec"] == "OPUS"

    async def peak(name: str) -> int:
        for entry in await api.call_local("receivers"):
            if entry["stream"] == name:
                return int(entry.get("peak", 0))
        return 0

    async def until_loud(name: str) -> None:
        while await peak(name) < 1000:
            await asyncio.sleep(0.05)

    await asyncio.wait_for(until_loud("audio_out"), 8)
    talking = await api.call_local("talk", platform_id="rover-v", test_tone=True)
    assert talking["state"] == "playing"
    platform_speaker = platform.ctx.media.streams["audio_in"]
    await wait_until(lambda: platform_speaker.hears_sound, timeout=8)
    assert (await api.call_local("talk", platform_id="rover-v", on=False))["state"] == "idle"
    await wait_until(lambda: platform_speaker.state.value == "idle")
    with pytest.raises(RpcError, match="no stream named 'audio_in' to receive"):
        await api.call_local("receive", platform_id="rover-v", stream="audio_in")


async def test_audio_command_hears_the_platform_talks_back_and_stops_both(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes
) -> None:
    platform = await sim_platform(
        platform_factory, fleet_key, "audio.enabled=true", f"audio.in_port={free_udp_port()}"
    )
    streams = platform.ctx.media.streams
    cli_run = asyncio.ensure_future(
        run_cli(
            station,
            "audio",
            "rover-v",
            "--url",
            platform.ctx.signaling_url,
            "--talk",
            "--test-tone",
            "--sink",
            "fakesink",
            "--seconds",
            "3",
            "--json",
        )
    )
    try:
        # While the command runs, the platform's speaker hears the station's test tone.
        await wait_until(lambda: streams["audio_in"].hears_sound, timeout=10)
    finally:
        code, out, err = await asyncio.wait_for(cli_run, 30)
    assert code == 0, err
    levels = [json.loads(line) for line in out.strip().splitlines()[2:]]
    assert levels
    assert levels[-1]["buffers"] > 0
    assert levels[-1]["peak"] > 1000
    # Ended: both directions stopped, on the platform and in the station daemon.
    assert "may still run" not in err
    await wait_until(lambda: streams["audio_in"].state.value == "idle", timeout=15)
    await wait_until(lambda: streams["audio_out"].state.value == "idle", timeout=15)
    assert await station.ctx.api.call_local("receivers") == []


async def test_stream_command_lists_starts_pauses_and_stops_one_stream(
    station: StationDaemon, platform_factory: Factory, fleet_key: bytes
) -> None:
    platform = await sim_platform(platform_factory, fleet_key)
    code, _, err = await run_cli(station, "connect", "rover-v", "--url", platform.ctx.signaling_url)
    assert code == 0, err
    code, out, err = await run_cli(station, "stream", "rover-v")
    assert code == 0, err
    assert re.search(r"^navcam\s+video_out\s+idle$", out, re.MULTILINE), out

    port = free_udp_port()
    code, out, err = await run_cli(
        station, "stream", "rover-v", "navcam", "start", "--port", str(port), "--json"
    )
    assert code == 0, err
    started = json.loads(out)
    assert started["state"] == "playing"
    assert started["destination"] == f"127.0.0.1:{port}"
    nav = platform.ctx.media.nav_camera
    code, out, err = await run_cli(station, "stream", "rover-v", "navcam", "pause")
    assert code == 0, err
    assert "paused" in out, err
    assert nav()["state"] == "paused"
    code, out, err = await run_cli(station, "stream", "rover-v", "navcam", "stop")
    assert code == 0, err
    assert "idle" in out, err
    assert nav()["state"] == "idle"

    code, out, err = await run_cli(station, "stream", "rover-v", "nosuch", "start")
    assert code == 1
    assert "nosuch" in err
    code, out, err = await run_cli(station, "stream", "rover-v", "navcam")
    assert code == 1
    assert "start, pause or stop" in err
