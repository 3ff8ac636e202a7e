"""Media: real GStreamer pipelines on loopback (NavCam out, station receiver, failures)."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

import pytest
from conftest import free_udp_port, quiet_platform_config, wait_until

from brasidas import topics
from brasidas.codecs.jsonrpc import INVALID_PARAMS, RpcError
from brasidas.media.gst import caps, gst, link_all, make
from brasidas.media.pipeline import PipelineStream, StreamState
from brasidas.media.video import VideoIn, VideoOut, VideoSettings
from brasidas.messages import StreamStatus
from platformd.app import PlatformDaemon
from stationd.client import PlatformConnection

Factory = Callable[..., Awaitable[PlatformDaemon]]


@pytest.fixture
async def receiver() -> AsyncIterator[VideoIn]:
    stream = VideoIn("rx", port=free_udp_port(), host="127.0.0.1")
    await stream.start()
    try:
        yield stream
    finally:
        await stream.stop()


async def open_session(daemon: PlatformDaemon, key: bytes) -> PlatformConnection:
    conn = PlatformConnection(
        daemon.config.platform.id, daemon.ctx.signaling_url, station_id="st-1", fleet_key=key
    )
    await conn.open()
    return conn


async def command(conn: PlatformConnection, code: int, payload: str = "") -> dict[str, Any]:
    answer: dict[str, Any] = await conn.call(
        "issue_system_command", group=10, command=code, payload=payload
    )
    return answer


async def frames_in(stream: VideoIn, seconds: float) -> int:
    before = stream.frames
    await asyncio.sleep(seconds)
    return stream.frames - before


async def test_navcam_streams_only_when_asked_and_carries_capture_time(
    platform_factory: Factory, fleet_key: bytes, receiver: VideoIn
) -> None:
    daemon = await platform_factory(
        quiet_platform_config(
            "sim.enabled=true", "navcam.enabled=true", f"navcam.port={receiver.port}"
        ),
        fleet_key,
    )
    states: list[StreamStatus] = []
    daemon.bus.subscribe(topics.STREAM_STATES, states.append)
    conn = await open_session(daemon, fleet_key)
    try:
        navcam = conn.capabilities["nav_camera"]
        assert (navcam["width"], navcam["height"], navcam["codec"]) == (640, 480, "H264")
        assert navcam["state"] == "idle"
        assert navcam["destination"] is None
        assert [s["name"] for s in conn.capabilities["streams"]] == ["navcam"]
        assert await frames_in(receiver, 0.3) == 0  # nothing until a station asks

        answer = await command(conn, 1, "host=127.0.0.1")
        assert answer["accepted"], answer
        await wait_until(lambda: receiver.stamped >= 3, timeout=8)
        assert receiver.latencies
        assert all(-50 < ms < 1000 for ms in receiver.latencies)
        # The sender counts what its encoder made (what a receiver's frames count against),
        # the receiver when its newest frame came (one clock for every process on the host).
        decoded = receiver.frames  # before the sender's count: every one of these was encoded
        streams = {s["name"]: s for s in await conn.call("list_streams")}
        assert streams["navcam"]["frames_encoded"] >= decoded >= 3
        described = receiver.describe()
        assert described["frames_depayloaded"] >= described["frames"] > 0
        shown_at = described["last_frame_monotonic"]
        assert 0 <= time.monotonic() - shown_at < 2
        assert states[-1].state == "playing"
        assert states[-1].destination.endswith(f":{receiver.port}")
        params = await conn.call("get_nav_camera_parameters")
        assert params["framerate"] == 5  # manual override disengaged (seed §3.2)
        assert params["destination"] == f"127.0.0.1:{receiver.port}"
        report = await conn.call("get_telemetry_report")
        assert report["streams"]["states"]["navcam"] == "playing"

        assert await conn.call("set_manual_override", engaged=True)
        assert (await conn.call("get_nav_camera_parameters"))["framerate"] == 30

        for payload, reason in (
            ("navcam=0", "1-30"),
            ("navcam=1000", "1-30"),
            ("navcam=fast", "integer"),
            ("rearcam=10", "no stream named 'rearcam'"),
            ("", "navcam=15"),
        ):
            answer = await command(conn, 5, payload)
            assert not answer["accepted"], (payload, answer)
            assert reason in answer["reason"], (payload, answer)
        answer = await command(conn, 5, "navcam=15")
        assert answer["accepted"]
        assert answer["result"] == {"navcam": 15}

        assert (await command(conn, 3))["accepted"]  # pause all
        await asyncio.sleep(0.2)
        assert await frames_in(receiver, 0.4) == 0
        assert states[-1].state == "paused", states[-1]
        assert (await command(conn, 1, "127.0.0.1"))["accepted"]  # resume (bare host payload)
        await wait_until(lambda: receiver.frames > 0 and states[-1].state == "playing")
        assert (await command(conn, 2))["accepted"]  # stop all
        assert states[-1].state == "idle"
    finally:
        await conn.close()


async def test_per_stream_methods_and_bad_names(
    platform_factory: Factory, fleet_key: bytes, receiver: VideoIn
) -> None:
    daemon = await platform_factory(
        quiet_platform_config("sim.enabled=true", "navcam.enabled=true"), fleet_key
    )
    conn = await open_session(daemon, fleet_key)
    try:
        with pytest.raises(RpcError) as info:
            await conn.call("start_stream", name="rearcam")
        assert info.value.code == INVALID_PARAMS
        assert "no stream named" in info.value.message
        with pytest.raises(RpcError, match="not an IP address"):
            await conn.call("start_stream", name="navcam", host="bad host!")
        started = await conn.call("start_stream", name="navcam", port=receiver.port)
        # No host given: the stream goes to the caller's own address.
        assert started["state"] == "playing"
        assert started["host"] == "127.0.0.1"
        await wait_until(lambda: receiver.frames > 0, timeout=8)
        assert (await conn.call("pause_stream", name="navcam"))["state"] == "paused"
        listed = await conn.call("list_streams")
        assert [(s["name"], s["state"]) for s in listed] == [("navcam", "paused")]
        assert (await conn.call("stop_stream", name="navcam"))["state"] == "idle"
        # A session that ends takes its streams with it.
        await conn.call("start_stream", name="navcam", port=receiver.port)
    finally:
        await conn.close()
    navcam = daemon.ctx.media.nav_camera
    await wait_until(lambda: navcam()["state"] == "idle")


async def test_missing_camera_fails_with_reason_and_is_retried(
    platform_factory: Factory, fleet_key: bytes
) -> None:
    daemon = await platform_factory(
        quiet_platform_config("navcam.enabled=true", "navcam.device=/dev/brasidas-no-camera"),
        fleet_key,
    )
    states: list[StreamStatus] = []
    daemon.bus.subscribe(topics.STREAM_STATES, states.append)
    stream = daemon.ctx.media.navcam
    stream.retry_initial = 0.05
    conn = await open_session(daemon, fleet_key)
    try:
        answer = await command(conn, 1, "host=127.0.0.1")
        assert not answer["accepted"]
        assert answer["result"] == {"navcam": "failed"}
        assert states[-1].state == "failed"
        assert "/dev/brasidas-no-camera" in states[-1].reason
        await wait_until(lambda: stream.retries >= 2, timeout=8)
        report = await conn.call("get_telemetry_report")
        assert report["streams"]["states"]["navcam"] == "failed"
        assert (await command(conn, 2))["accepted"]
        retries = stream.retries
        await asyncio.sleep(0.3)
        assert stream.retries == retries
        assert stream.state is StreamState.IDLE
    finally:
        await conn.close()


async def test_a_failed_stream_leaves_the_others_running(receiver: VideoIn) -> None:
    good = VideoOut("good", VideoSettings(test_source=True, port=receiver.port))
    bad = VideoOut("bad", VideoSettings(test_source=True, encoder="omxh264enc"))
    broken = VideoOut("broken", VideoSettings(test_source=True, pattern="no-such-pattern"))
    try:
        assert await good.start() is StreamState.PLAYING
        assert await bad.start() is StreamState.FAILED
        assert "omxh264enc" in bad.reason
        assert await broken.start() is StreamState.FAILED
        assert "no-such-pattern" in broken.reason or "pattern" in broken.reason
        before = receiver.frames
        await wait_until(lambda: receiver.frames > before + 5, timeout=8)
    finally:
        for stream in (good, bad, broken):
            await stream.stop()


async def test_station_not_listening_is_not_a_failure() -> None:
    stream = VideoOut("navcam", VideoSettings(test_source=True, port=free_udp_port()))
    try:
        assert await stream.start() is StreamState.PLAYING
        await asyncio.sleep(0.5)  # ICMP port unreachable comes back; the sender carries on
        assert stream.state is StreamState.PLAYING
    finally:
        await stream.stop()


class VanishingCamera(VideoOut):
    """A source that stops after 20 frames, as a USB camera unplugged mid-stream."""

    def _source_elements(self) -> list[Any]:
        elements = super()._source_elements()
        elements[0].set_property("num-buffers", 20)
        return elements


async def test_camera_lost_mid_stream_fails_and_comes_back(receiver: VideoIn) -> None:
    stream = VanishingCamera(
        "navcam", VideoSettings(test_source=True, port=receiver.port), retry_initial=0.1
    )
    reasons: list[str] = []
    stream.on_change = lambda s: reasons.append(s.reason) if s.state is StreamState.FAILED else None
    async with asyncio.TaskGroup() as group:
        supervisor = group.create_task(stream.supervise())
        try:
            assert await stream.start() is StreamState.PLAYING
            await wait_until(lambda: stream.retries >= 1, timeout=8)
            assert reasons
            assert "end of stream" in reasons[0]
            frames = receiver.frames
            await wait_until(lambda: receiver.frames > frames, timeout=8)  # rebuilt, flowing
        finally:
            await stream.stop()
            supervisor.cancel()


async def test_a_framerate_asked_inside_a_renegotiation_waits_for_it(receiver: VideoIn) -> None:
    """A framerate asked while the streaming thread is inside the camera's caps query, which
    the previous change started (held open here by a probe), waits for it: the stream keeps
    playing, at the last framerate asked. Set at once from the event loop, the rate filter's
    caps changed between the query's two halves (30 fps down, 15 back): an empty answer, the
    source stopped with "not-negotiated", a failed stream (the override's 30 fps, then
    ``navcam=15``, under load)."""
    Gst = gst()
    stream = VideoOut("navcam", VideoSettings(test_source=True, port=receiver.port, framerate=5))
    armed, in_query, resume = threading.Event(), threading.Event(), threading.Event()
    source_asked: list[bool] = []
    held: list[bool] = []

    def source_asks(pad: Any, info: Any) -> Any:
        query = info.get_query()
        if armed.is_set() and query is not None and query.type == Gst.QueryType.CAPS:
            source_asked.append(True)
        return Gst.PadProbeReturn.OK

    def hold_the_source_query(pad: Any, info: Any) -> Any:
        query = info.get_query()
        if query is not None and query.type == Gst.QueryType.CAPS and source_asked and not held:
            held.append(True)
            in_query.set()
            resume.wait(5)
        return Gst.PadProbeReturn.OK

    try:
        assert await stream.start() is StreamState.PLAYING
        await wait_until(lambda: receiver.frames >= 2, timeout=8)
        queries = Gst.PadProbeType.QUERY_DOWNSTREAM
        source = stream.pipeline.get_by_name("source")
        source.get_static_pad("src").add_probe(queries, source_asks)
        rate = stream.pipeline.get_by_name("rate")
        rate.get_static_pad("src").add_probe(queries, hold_the_source_query)
        armed.set()
        stream.set_framerate(30)  # the camera renegotiates: held inside its caps query
        assert await asyncio.to_thread(in_query.wait, 5)
        stream.set_framerate(15)
        resume.set()
        frames = receiver.frames
        failed = lambda: stream.state is StreamState.FAILED  # noqa: E731
        await wait_until(lambda: receiver.frames > frames + 10 or failed(), timeout=8)
        assert stream.state is StreamState.PLAYING, stream.reason
        assert stream.failures == 0
        encoder = stream.pipeline.get_by_name("encoder")
        fed = encoder.get_static_pad("sink").get_current_caps().get_structure(0)
        assert fed.get_fraction("framerate")[1:] == (15, 1)
    finally:
        resume.set()
        await stream.stop()


class _Unnegotiable(PipelineStream):
    """A live source whose two filters ask for different sizes: nothing negotiates."""

    def build(self) -> Any:
        pipeline = gst().Pipeline.new("unnegotiable")
        small, large = make("capsfilter"), make("capsfilter")
        chain = [make("videotestsrc", "source", is_live=True), small, large, make("fakesink")]
        for element in chain:
            pipeline.add(element)
        link_all(*chain)
        small.set_property("caps", caps("video/x-raw,width=320"))  # after linking: at runtime
        large.set_property("caps", caps("video/x-raw,width=640"))
        return pipeline


async def test_a_failure_says_why_the_streaming_stopped() -> None:
    """GStreamer's "Internal data stream error" says nothing by itself: the reason carries
    the cause from its debug string (the next failure nobody can reproduce is readable)."""
    stream = _Unnegotiable("unnegotiable")
    try:
        await stream.start()
        await wait_until(lambda: stream.state is StreamState.FAILED, timeout=5)
        assert stream.reason.startswith("source: Internal data stream error"), stream.reason
        assert "reason not-negotiated" in stream.reason, stream.reason
    finally:
        await stream.stop()


def slices_per_access_unit(data: bytes) -> int:
    """Coded slice NAL units (types 1 and 5) in one AVC access unit (4-byte lengths)."""
    count, index = 0, 0
    while index + 4 < len(data):
        length = int.from_bytes(data[index : index + 4], "big")
        if data[index + 4] & 0x1F in (1, 5):
            count += 1
        index += 4 + length
    return count


async def test_every_frame_is_one_slice(receiver: VideoIn) -> None:
    """Chromium decodes multi-slice H.264 wrongly: the web console needs one slice per frame."""
    Gst = gst()
    counts: list[int] = []

    def probe(pad: Any, info: Any) -> Any:
        buffer = info.get_buffer()
        ok, mapped = buffer.map(Gst.MapFlags.READ)
        if ok:
            counts.append(slices_per_access_unit(bytes(mapped.data)))
            buffer.unmap(mapped)
        return Gst.PadProbeReturn.OK

    depay = receiver.pipeline.get_by_name("depay")
    depay.get_static_pad("src").add_probe(Gst.PadProbeType.BUFFER, probe)
    stream = VideoOut(
        "navcam", VideoSettings(test_source=True, pattern="smpte", motion=4, port=receiver.port)
    )
    try:
        await stream.start()
        await wait_until(lambda: len(counts) >= 45, timeout=8)  # 1.5 s: keyframes included
    finally:
        await stream.stop()
    assert set(counts) == {1}, counts


class _StuckPipeline:
    """Stands in for a GStreamer pipeline whose NULL transition never returns (the
    rtpjitterbuffer deadlock seen once in CI): everything else answers at once."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.bus_touched_after_null = False
        self._nulling = False

    def use_clock(self, clock: object) -> None:
        pass

    def get_bus(self) -> _StuckPipeline:
        self.bus_touched_after_null = self.bus_touched_after_null or self._nulling
        return self

    def set_sync_handler(self, *args: object) -> None:
        pass

    def iterate_sources(self) -> object:
        self._empty = gst().Bin.new("empty")  # no sources: an iterator that ends at once
        return self._empty.iterate_sources()

    def set_state(self, state: object) -> object:
        Gst = gst()
        if state == Gst.State.NULL:
            self._nulling = True
            self.release.wait()  # never set: stuck, like the deadlocked set_state
        return Gst.StateChangeReturn.SUCCESS


class _StuckStream(PipelineStream):
    def __init__(self) -> None:
        super().__init__("stuck", state_change_timeout=0.3)
        self.fake = _StuckPipeline()

    def build(self) -> object:
        return self.fake


async def test_a_state_change_that_never_returns_is_abandoned_not_waited_for() -> None:
    stream = _StuckStream()
    assert await stream.start() is StreamState.PLAYING
    await asyncio.wait_for(stream.stop(), 5)  # not forever
    assert stream.state is StreamState.IDLE
    assert stream.abandoned == 1
    assert not stream.fake.bus_touched_after_null
    (stuck,) = [t for t in threading.enumerate() if t.name == "gst-state:stuck"]
    assert stuck.daemon  # the process can still exit
    stream.fake.release.set()
