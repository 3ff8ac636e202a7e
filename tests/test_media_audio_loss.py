"""Audio over a lossy link (issue 28): Opus in-band FEC and loss concealment keep the sound
whole, where each lost packet used to be 20 ms of silence missing from the stream."""

from __future__ import annotations

import asyncio

from conftest import free_udp_port, wait_until
from lossy_udp import LossyRelay

from brasidas.media.audio import AudioIn, AudioOut, AudioSettings

RATE = 48_000


async def test_lost_audio_packets_are_rebuilt_or_concealed() -> None:
    # Two receivers behind two links losing the same packets (same seed), side by side on
    # the same machine: one conceals, one does not (as before), so load affects both alike.
    ports = [free_udp_port(), free_udp_port()]
    relays = [LossyRelay(("127.0.0.1", port), loss=0.10, seed=3) for port in ports]
    conceals = AudioIn("conceals", port=ports[0], sink="fakesink")
    plain = AudioIn("plain", port=ports[1], sink="fakesink", conceal=False)
    sender = AudioOut("mic", AudioSettings(test_source=True, port=relays[0].port))
    sender.set_destinations([("127.0.0.1", relays[0].port), ("127.0.0.1", relays[1].port)])
    try:
        for receiver in (conceals, plain):
            await receiver.start()
        await sender.start()
        await wait_until(lambda: min(conceals.samples, plain.samples) > RATE // 2, timeout=10)
        before = (conceals.samples, plain.samples, relays[0].dropped)
        await asyncio.sleep(4)
        dropped_s = (relays[0].dropped - before[2]) * 0.020
        gained_s = (conceals.samples - before[0] - (plain.samples - before[1])) / RATE
        assert dropped_s >= 0.2  # ~20 of 200 packets lost on the way
        # Most of the lost 20 ms came back (from FEC, or concealed) where they used to be gone.
        assert gained_s >= 0.6 * dropped_s, (gained_s, dropped_s)
        assert conceals.hears_sound
    finally:
        await sender.stop()
        for receiver in (conceals, plain):
            await receiver.stop()
        for relay in relays:
            relay.close()
