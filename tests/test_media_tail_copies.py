"""A low framerate's frames end with their last packet sent twice: a lost last packet shows
at the receiver only when the next frame's first arrives (at 5 fps, 200 ms on), so without
the copy its frame came a frame late."""

from __future__ import annotations

import socket
import statistics
import threading

from conftest import free_udp_port, wait_until

from brasidas.media.video import PAYLOAD_TYPE, VideoIn, VideoOut, VideoSettings


class _FirstTailLost:
    """A loopback UDP relay that loses the first copy of every frame's last packet (RTP
    marker set): the worst case of a lossy link, made certain."""

    def __init__(self, to: tuple[str, int]) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port: int = self.sock.getsockname()[1]
        self.to = to
        self.dropped = 0
        self._seen: set[int] = set()
        self._running = True
        self._thread = threading.Thread(target=self._run, name="tail-loss", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while self._running:
            try:
                data, _ = self.sock.recvfrom(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            if len(data) >= 4 and data[1] == 0x80 | PAYLOAD_TYPE:
                seq = int.from_bytes(data[2:4], "big")
                if seq not in self._seen:
                    self._seen.add(seq)
                    self.dropped += 1
                    continue
            self.sock.sendto(data, self.to)

    def close(self) -> None:
        self._running = False
        self._thread.join(2)
        self.sock.close()


async def test_at_5_fps_a_frame_whose_last_packet_is_lost_still_comes_on_time() -> None:
    port = free_udp_port()
    receiver = VideoIn("rx", host="127.0.0.1", port=port)
    await receiver.start()
    relay = _FirstTailLost(("127.0.0.1", port))
    settings = VideoSettings(
        test_source=True, host="127.0.0.1", port=relay.port, framerate=5, pattern="smpte"
    )
    sender = VideoOut("navcam", settings)
    try:
        await sender.start()
        assert sender.feedback is not None
        receiver.set_feedback("127.0.0.1", sender.feedback.port)  # it may ask (NACK) too
        await wait_until(lambda: receiver.stamped >= 15, timeout=30)
        assert relay.dropped >= 15  # every frame lost its last packet once
        assert sender.describe()["tail_copies"] >= 15
        # Each frame complete as it was sent. Without the copy each waited for the next
        # frame to show the loss, then for its repair: a median over 200 ms at 5 fps.
        latencies = list(receiver.latencies)[5:]
        assert statistics.median(latencies) < 100, latencies
    finally:
        await sender.stop()
        await receiver.stop()
        relay.close()


async def test_at_30_fps_no_copies_are_sent() -> None:
    port = free_udp_port()
    receiver = VideoIn("rx", host="127.0.0.1", port=port)
    await receiver.start()
    sender = VideoOut("navcam", VideoSettings(test_source=True, host="127.0.0.1", port=port))
    try:
        await sender.start()
        await wait_until(lambda: receiver.frames >= 30, timeout=20)
        # The next frame is 33 ms away: a lost last packet shows soon enough.
        assert sender.describe()["tail_copies"] == 0
    finally:
        await sender.stop()
        await receiver.stop()
