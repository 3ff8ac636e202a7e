"""Media: NavCam glass-to-glass latency, bitrate, platform CPU and RSS, on loopback.

A real ``brasidas-platform --sim`` child streams its NavCam (640x480@30 with the manual
override engaged, software encoder, moving ``smpte`` pattern so the bitrate is honest) to a
receive pipeline in this process; 10.1 also starts two-way audio (the platform's test tone
to a receiver here, a test tone from here to the platform's speaker), so CPU and RSS are
those of a platform streaming everything. Latency is capture stamp (RFC 6051 NTP-64 header extension,
taken at the source) to frame decoded here, per frame, over ``WINDOW_S``. Bitrate counts RTP
bytes (UDP/IP headers excluded). CPU and RSS are the platform process's.
"""

from __future__ import annotations

import asyncio
import os
import resource
import socket
import time
from typing import Any

from bench.support import (
    connect_to_platform,
    cpu_seconds,
    free_port,
    percentiles,
    rss_mb,
    start_platform,
)
from brasidas.media.audio import AudioIn, AudioOut, AudioSettings
from brasidas.media.video import VideoIn

WINDOW_S = float(os.environ.get("BENCH_MEDIA_SECONDS", "20"))
IDLE_WINDOW_S = 5.0


def _own_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


async def _window(receiver: VideoIn, pid: int, seconds: float) -> dict[str, Any]:
    receiver.latencies.clear()
    frames, rtp_bytes = receiver.frames, receiver.rtp_bytes
    cpu, own = cpu_seconds(pid), _own_cpu()
    started = time.monotonic()
    await asyncio.sleep(seconds)
    elapsed = time.monotonic() - started
    return {
        "latencies": list(receiver.latencies),
        "fps": round((receiver.frames - frames) / elapsed, 1),
        "mbps": round((receiver.rtp_bytes - rtp_bytes) * 8 / elapsed / 1e6, 3),
        "platform_cpu_pct": round((cpu_seconds(pid) - cpu) / elapsed * 100, 1),
        "receiver_cpu_pct": round((_own_cpu() - own) / elapsed * 100, 1),
    }


async def run() -> dict[str, Any]:
    signaling_port = free_port()
    video_port = free_port(socket.SOCK_DGRAM)
    audio_out_port, audio_in_port = free_port(socket.SOCK_DGRAM), free_port(socket.SOCK_DGRAM)
    process = await start_platform(
        f"signaling.port={signaling_port}",
        "beacon.enabled=false",
        "navcam.enabled=true",
        f"navcam.port={video_port}",
        "navcam.sim_pattern=smpte",
        "navcam.sim_motion=4",
        "audio.enabled=true",
        f"audio.out_port={audio_out_port}",
        f"audio.in_port={audio_in_port}",
    )
    receiver = VideoIn("bench", host="127.0.0.1", port=video_port, window=100_000)
    speaker = AudioIn("bench-speaker", port=audio_out_port, sink="fakesink")
    microphone = AudioOut("bench-mic", AudioSettings(test_source=True, port=audio_in_port))
    figures: dict[str, Any] = {}
    try:
        connection = await connect_to_platform(signaling_port)
        try:
            await receiver.start()
            await speaker.start()
            rss_before = rss_mb(process.pid)
            answer = await connection.call(
                "issue_system_command", group=10, command=1, payload="host=127.0.0.1"
            )
            if not answer.get("accepted"):
                raise RuntimeError(f"10.1 refused: {answer}")
            await microphone.start()
            # Override disengaged: 5 fps.
            await asyncio.sleep(1.5)
            idle = await _window(receiver, process.pid, IDLE_WINDOW_S)
            await connection.call("set_manual_override", engaged=True)
            await asyncio.sleep(1.5)
            busy = await _window(receiver, process.pid, WINDOW_S)
            params = await connection.call("get_nav_camera_parameters")
            streams = {s["name"]: s for s in await connection.call("list_streams")}
            latency = percentiles(busy["latencies"]) if busy["latencies"] else {}
            figures = {
                "encoder": params.get("encoder"),
                "resolution": f"{params.get('width')}x{params.get('height')}",
                "window_s": WINDOW_S,
                "frames_measured": len(busy["latencies"]),
                "glass_to_glass_p50_ms": latency.get("p50"),
                "glass_to_glass_p99_ms": latency.get("p99"),
                "glass_to_glass_mean_ms": latency.get("mean"),
                "fps_engaged": busy["fps"],
                "bitrate_mbps_engaged_moving": busy["mbps"],
                "bitrate_kbps_setting": params.get("bitrate_kbps"),
                "platform_cpu_pct_one_core_30fps_and_audio": busy["platform_cpu_pct"],
                "receiver_cpu_pct_one_core_30fps_and_audio": busy["receiver_cpu_pct"],
                "fps_idle": idle["fps"],
                "bitrate_mbps_idle_5fps": idle["mbps"],
                "platform_cpu_pct_one_core_5fps_and_audio": idle["platform_cpu_pct"],
                "platform_rss_mb_before_stream": rss_before,
                "platform_rss_mb_navcam_and_audio": rss_mb(process.pid),
                "audio_out_heard": speaker.hears_sound,
                "audio_out_buffers": speaker.buffers,
                "audio_in_peak_at_platform": streams.get("audio_in", {}).get("peak"),
            }
            await connection.call("issue_system_command", group=10, command=2, payload="")
        finally:
            await connection.close()
    finally:
        for stream in (receiver, speaker, microphone):
            await stream.stop()
        process.terminate()
        try:
            await asyncio.wait_for(process.wait(), 5)
        except TimeoutError:
            process.kill()
            await process.wait()
    return figures
