"""The attacker of ``bench_hostile``: a host without the fleet key, run inside its namespace.

    python -m bench.hostile_peer flood HOST PORT SECONDS CONNECTIONS
    python -m bench.hostile_peer idle HOST PORT COUNT HOLD_SECONDS
    python -m bench.hostile_peer partial HOST PORT COUNT WAIT_SECONDS

``flood``: each connection posts the issue's 64 KiB batch of 21,000 ``{}`` as fast as it is
answered (reconnecting when closed). ``idle``: COUNT connections that never send a byte, held
for HOLD_SECONDS. ``partial``: COUNT connections that send half a request's headers, then
wait for the platform to close each. Prints one JSON line of figures at the end.
"""

from __future__ import annotations

import asyncio
import json
import socket
import sys
import time
from typing import Any

BATCH = b"[" + b",".join([b"{}"] * 21_000) + b"]"


async def flood(host: str, port: int, seconds: float, connections: int) -> dict[str, Any]:
    request = (
        f"POST /rpc HTTP/1.1\r\nHost: {host}:{port}\r\nContent-Type: application/json\r\n"
        f"Content-Length: {len(BATCH)}\r\n\r\n"
    ).encode() + BATCH
    figures = {"requests": 0, "answered_bytes": 0, "reconnects": 0}
    deadline = time.monotonic() + seconds

    async def one() -> None:
        while time.monotonic() < deadline:
            try:
                reader, writer = await asyncio.open_connection(host, port)
            except OSError:
                await asyncio.sleep(0.01)
                continue
            figures["reconnects"] += 1
            try:
                while time.monotonic() < deadline:
                    writer.write(request)
                    head = await reader.readuntil(b"\r\n\r\n")
                    length = 0
                    for line in head.split(b"\r\n"):
                        if line.lower().startswith(b"content-length:"):
                            length = int(line.split(b":")[1])
                    body = await reader.readexactly(length)
                    figures["requests"] += 1
                    figures["answered_bytes"] += len(head) + len(body)
            except (OSError, asyncio.IncompleteReadError, asyncio.LimitOverrunError):
                pass
            finally:
                writer.close()

    await asyncio.gather(*(one() for _ in range(connections)))
    return figures


def _open(host: str, port: int, count: int) -> list[socket.socket]:
    opened = []
    for _ in range(count):
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        sock.setblocking(False)
        sock.connect_ex((host, port))
        opened.append(sock)
    return opened


async def _closed_after(sock: socket.socket, limit: float) -> float | None:
    """Seconds until the server closed ``sock`` (None: still open after ``limit``)."""
    loop = asyncio.get_running_loop()
    started = time.monotonic()
    try:
        async with asyncio.timeout(limit):
            while await loop.sock_recv(sock, 4096):
                pass
    except TimeoutError:
        return None
    except OSError:
        pass
    return time.monotonic() - started


async def idle(host: str, port: int, count: int, hold: float) -> dict[str, Any]:
    opened = _open(host, port, count)
    await asyncio.sleep(0.5)
    waits = await asyncio.gather(*(_closed_after(sock, hold) for sock in opened))
    for sock in opened:
        sock.close()
    return {"opened": count, "closed_by_platform": sum(wait is not None for wait in waits)}


async def partial(host: str, port: int, count: int, wait: float) -> dict[str, Any]:
    opened = _open(host, port, count)
    loop = asyncio.get_running_loop()
    half = f"POST /rpc HTTP/1.1\r\nHost: {host}:{port}\r\n".encode()

    async def send(sock: socket.socket) -> None:
        try:
            await asyncio.wait_for(loop.sock_sendall(sock, half), 5)
        except (OSError, TimeoutError):
            pass  # closed already (refused over the host's cap)

    await asyncio.gather(*(send(sock) for sock in opened))
    waits = await asyncio.gather(*(_closed_after(sock, wait) for sock in opened))
    for sock in opened:
        sock.close()
    closed = sorted(w for w in waits if w is not None)
    return {
        "opened": count,
        "closed": len(closed),
        "still_open": count - len(closed),
        "last_closed_s": round(closed[-1], 2) if closed else None,
    }


def main(argv: list[str]) -> int:
    mode, host, port, *rest = argv
    if mode == "flood":
        figures = asyncio.run(flood(host, int(port), float(rest[0]), int(rest[1])))
    elif mode == "idle":
        figures = asyncio.run(idle(host, int(port), int(rest[0]), float(rest[1])))
    elif mode == "partial":
        figures = asyncio.run(partial(host, int(port), int(rest[0]), float(rest[1])))
    else:
        raise SystemExit(f"unknown mode {mode}")
    print(json.dumps(figures), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
