"""Audio over a lossy link (issue 28): Opus in-band FEC and loss concealment keep the sound
whole, where each lost packet used to be 20 ms of silence missing from the stream."""

from __future__ import annotations

import asyncio
import time

from conftest import free_udp_port, wait_until
from lossy_udp import LossyRelay

from brasidas.media.audio import AudioIn, AudioOut, AudioSettings

RATE = 48_000


async def test_lost_audio_packets_are_rebuilt_or_concealed() -> None:
    port = free_udp_port()
    relay = LossyRelay(("127.0.0.1", port), loss=0.10)
    receiver = AudioIn("rx", port=port, sink="fakesink")
    sender = AudioOut("mic", AudioSettings(test_source=True, port=relay.port))
    try:
        await receiver.start()
        await sender.start()
        await wait_until(lambda: receiver.samples > RATE // 2, timeout=10)
        samples, dropped, started = receiver.samples, relay.dropped, time.monotonic()
        await asyncio.sleep(4)
        decoded_s = (receiver.samples - samples) / RATE
        elapsed = time.monotonic() - started
        assert relay.dropped - dropped >= 10  # ~20 of 200 packets lost on the way
        # Every 20 ms is there: the lost ones came back from FEC or were concealed.
        assert decoded_s >= 0.97 * elapsed, (decoded_s, elapsed)
        assert receiver.hears_sound
    finally:
        await sender.stop()
        await receiver.stop()
        relay.close()
