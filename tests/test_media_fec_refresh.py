"""Frames that degrade gracefully (intra refresh) and forward error correction (ULPFEC): a lost
packet rebuilt at the receiver with no retransmission, no keyframe bursts, keyframes still made
on request."""

from __future__ import annotations

import asyncio
import statistics
import threading

from conftest import free_udp_port, wait_until
from lossy_udp import LossyRelay

from brasidas.media.repair import fec_percentage
from brasidas.media.video import VideoIn, VideoOut, VideoSettings


def test_the_fec_share_follows_the_loss_within_its_bound() -> None:
    assert fec_percentage(0.0, 30) == 0  # a clean link carries no FEC (nor its overhead)
    assert fec_percentage(0.005, 30) == 0
    assert fec_percentage(0.02, 30) == 5
    assert fec_percentage(0.05, 30) == 15
    assert fec_percentage(0.10, 30) == 30
    assert fec_percentage(0.30, 30) == 30  # never beyond the configured most
    assert fec_percentage(0.10, 0) == 0  # switched off


def test_fec_is_carried_within_the_bitrate() -> None:
    stream = VideoOut("navcam", VideoSettings(bitrate_kbps=1300))
    stream.fec_percent = 30
    assert stream.media_bitrate_kbps() == 1000  # media + 30 % FEC = the budget


async def test_a_lost_packet_is_rebuilt_from_fec_without_retransmission() -> None:
    port = free_udp_port()
    receiver = VideoIn("rx", host="127.0.0.1", port=port, fec=True)
    await receiver.start()
    relay = LossyRelay(("127.0.0.1", port), loss=0.05, seed=3)
    settings = VideoSettings(
        test_source=True, host="127.0.0.1", port=relay.port, pattern="smpte", motion=4
    )
    sender = VideoOut("navcam", settings)
    try:
        await sender.start()
        # The receiver is never told the sender's RTCP port: it cannot ask for anything.
        assert sender.pipeline is not None
        sender.pipeline.get_by_name("fecenc").set_property("percentage", 30)
        sender.fec_percent = 30

        def rebuilt() -> int:
            repair = receiver.describe().get("repair") or {}
            return int(repair.get("fec_recovered", 0))

        await wait_until(lambda: rebuilt() >= 5, timeout=20)
        stats = receiver.describe()
        assert stats["repair"]["repaired"] == 0  # no retransmission arrived
        assert sender.retransmissions().get("retransmitted", 0) == 0
        assert relay.dropped > 0
    finally:
        await sender.stop()
        await receiver.stop()
        relay.close()


class _Units:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.units: list[tuple[int, bool]] = []

    def __call__(self, annex_b: bytes, keyframe: bool, captured_ns: int) -> None:
        with self._lock:
            self.units.append((len(annex_b), keyframe))

    def since(self, start: int) -> list[tuple[int, bool]]:
        with self._lock:
            return self.units[start:]


async def test_intra_refresh_has_no_keyframe_bursts() -> None:
    units = _Units()
    settings = VideoSettings(
        test_source=True,
        port=free_udp_port(),
        encoder="x264enc",
        pattern="smpte",
        motion=4,
        intra_refresh=True,
    )
    stream = VideoOut("navcam", settings)
    stream.access_unit_sinks.append(units)
    try:
        await stream.start()
        assert stream.describe()["intra_refresh"] is True
        await wait_until(lambda: len(units.since(0)) >= 100, timeout=15)
        # Three seconds at 30 fps, once the rate control settled after the first IDR.
        sizes = [size for size, _ in units.since(30)[:60]]
        # Periodic keyframes were about twice the other frames once a second.
        assert max(sizes) < 1.4 * statistics.median(sizes), sizes
    finally:
        await stream.stop()


async def test_without_intra_refresh_the_keyframes_come_every_second() -> None:
    units = _Units()
    settings = VideoSettings(
        test_source=True, port=free_udp_port(), encoder="x264enc", intra_refresh=False
    )
    stream = VideoOut("navcam", settings)
    stream.access_unit_sinks.append(units)
    try:
        await stream.start()
        await wait_until(lambda: len(units.since(0)) >= 70, timeout=15)
        await asyncio.sleep(0)
        assert sum(key for _, key in units.since(0)[:70]) >= 2
    finally:
        await stream.stop()
