"""A UDP relay on loopback that drops a share of the datagrams (seeded): a lossy link for
tests that need one without the namespace network."""

from __future__ import annotations

import random
import socket
import threading


class LossyRelay:
    """Receives on ``port`` and forwards to ``to``, dropping ``loss`` of the datagrams."""

    def __init__(self, to: tuple[str, int], loss: float, seed: int = 1) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.1)
        self.port: int = self.sock.getsockname()[1]
        self.to = to
        self.loss = loss
        self.dropped = 0
        self.forwarded = 0
        self._random = random.Random(seed)
        self._running = True
        self._thread = threading.Thread(target=self._run, name="lossy-relay", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while self._running:
            try:
                data, _ = self.sock.recvfrom(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            if self.lost(data):
                self.dropped += 1
                continue
            self.forwarded += 1
            self.sock.sendto(data, self.to)

    def lost(self, data: bytes) -> bool:
        """Whether this datagram is lost on the way (a seeded share of them)."""
        return self._random.random() < self.loss

    def close(self) -> None:
        self._running = False
        self._thread.join(2)
        self.sock.close()
