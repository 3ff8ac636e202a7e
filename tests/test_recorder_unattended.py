"""The recorder records the camera when nobody watches (issue 28): its own copy of the NavCam
at ``recorder.video_fps``, sent nowhere, from the same encoder a station's copy then uses."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Awaitable, Callable
from pathlib import Path

from conftest import free_udp_port, quiet_platform_config, wait_until
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader
from support.velocity import open_connection

from brasidas.media.video import VideoOut
from platformd.app import PlatformDaemon

Factory = Callable[..., Awaitable[PlatformDaemon]]


class _Frames:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.count = 0

    def __call__(self, annex_b: bytes, keyframe: bool, captured_ns: int) -> None:
        with self._lock:
            self.count += 1


async def test_an_unwatched_platform_records_its_camera(
    platform_factory: Factory, fleet_key: bytes, tmp_path: Path
) -> None:
    recordings = tmp_path / "recordings"
    daemon = await platform_factory(
        quiet_platform_config(
            "platform.id=rover-alone",
            "sim.enabled=true",
            "navcam.enabled=true",
            "navcam.idle_framerate=5",
            "recorder.enabled=true",
            f"recorder.dir={recordings}",
            "recorder.video_fps=10",
            "recorder.chunk_seconds=0.2",
        ),
        fleet_key,
    )
    media = daemon.ctx.media
    assert media is not None
    assert isinstance(media.navcam, VideoOut)
    navcam = media.navcam
    frames = _Frames()
    await wait_until(lambda: navcam.state.value == "playing", timeout=20)
    navcam.access_unit_sinks.append(frames)
    await wait_until(lambda: frames.count >= 20, timeout=20)
    described = navcam.describe()
    assert described["destinations"] == []
    assert described["framerate"] == 10

    # A station watches: the same pipeline, at the mode's rate, to the station's port ...
    conn = await open_connection(daemon, fleet_key)
    port = free_udp_port()
    try:
        await conn.call("start_stream", name="navcam", port=port)
        described = navcam.describe()
        assert described["destinations"] == [f"127.0.0.1:{port}"]
        assert described["framerate"] == 5
        # ... and when it stops watching, the recorder's own copy goes on.
        await conn.call("stop_stream", name="navcam")
        assert navcam.state.value == "playing"
        assert navcam.describe()["destinations"] == []
        assert navcam.describe()["framerate"] == 10
    finally:
        await conn.close()

    # The file being written holds the video nobody watched.
    def recorded_video() -> int:
        return sum(navcam_messages(path) for path in recordings.glob("*.mcap*"))

    await wait_until(lambda: recorded_video() >= 20, timeout=20)


def navcam_messages(path: Path) -> int:
    """The /navcam messages of a file, finished or still being written."""
    topics: dict[int, str] = {}
    count = 0
    with open(path, "rb") as stream:
        with contextlib.suppress(Exception):  # the record being written
            for record in StreamReader(stream).records:
                if isinstance(record, Channel):
                    topics[record.id] = record.topic
                elif isinstance(record, Message) and topics.get(record.channel_id) == "/navcam":
                    count += 1
    return count
