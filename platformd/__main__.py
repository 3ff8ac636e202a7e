"""``brasidas-platform`` and ``python -m platformd``.

The platform makes no TLS connection: signaling is plain HTTP on the mesh, authenticated with
the fleet key (R-0.9), and the RTSP camera is GStreamer's. Importing Python's ``ssl`` module
(which asyncio and aiohttp do when they can) costs the daemon about 4 MB of resident memory,
a tenth of its budget on a Raspberry Pi, so the entry point keeps it out before anything
imports asyncio; both treat a missing ``ssl`` as "no TLS".
"""

import sys


def run() -> int:
    sys.modules.setdefault("ssl", None)  # type: ignore[arg-type]
    from platformd.cli import main

    return main()


if __name__ == "__main__":
    sys.exit(run())
