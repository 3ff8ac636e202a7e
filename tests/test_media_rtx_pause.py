"""While a link's queue overflows the sender drops its retransmissions (they only feed the
queue); once it drains it sends them again. The dropping is on the retransmitter's pad only
while it drops: every packet passes there, and a probe that only looked would take the GIL
on the streaming thread for each one."""

from __future__ import annotations

import asyncio

from conftest import free_udp_port, wait_until
from lossy_udp import LossyRelay

from brasidas.media.video import VideoIn, VideoOut, VideoSettings


async def test_retransmissions_are_dropped_while_the_queue_overflows_and_sent_after() -> None:
    port = free_udp_port()
    receiver = VideoIn("rx", host="127.0.0.1", port=port)
    await receiver.start()
    relay = LossyRelay(("127.0.0.1", port), loss=0.1, seed=5)
    settings = VideoSettings(
        test_source=True, host="127.0.0.1", port=relay.port, pattern="smpte", motion=4
    )
    sender = VideoOut("navcam", settings)
    loop = asyncio.get_running_loop()
    try:
        await sender.start()
        assert sender.feedback is not None
        receiver.set_feedback("127.0.0.1", sender.feedback.port)  # it asks (NACK)

        def sent_again() -> int:
            return int(sender.retransmissions().get("retransmitted", 0))

        await wait_until(lambda: sent_again() >= 3, timeout=20)
        assert sender.retransmissions_dropped == 0
        # The controller saw the queue overflow: retransmissions are dropped.
        sender.bitrate.overused_at = loop.time()
        sender.adapt_bitrate(loop.time())
        assert not sender.retransmit
        await wait_until(lambda: sender.retransmissions_dropped >= 3, timeout=20)
        # It drained: they go out again, none dropped.
        sender.bitrate.overused_at = None
        sender.adapt_bitrate(loop.time())
        assert sender.retransmit
        dropped, before = sender.retransmissions_dropped, sent_again()
        await wait_until(lambda: sent_again() >= before + 3, timeout=20)
        assert sender.retransmissions_dropped == dropped
    finally:
        await sender.stop()
        await receiver.stop()
        relay.close()
