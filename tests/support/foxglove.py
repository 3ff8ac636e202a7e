"""The Foxglove test client (``@foxglove/ws-protocol``, Node) as a coroutine."""

from __future__ import annotations

import asyncio
import json
import os
import shutil
from pathlib import Path
from typing import Any

CLIENT = Path(__file__).resolve().parents[1] / "foxglove_client"
"""The client script; its packages are the repository's (package.json, ``make deps``)."""
NODE = shutil.which("node")


async def subscribe(
    port: int, count: int, *topics: str, offer: str | None = None
) -> list[dict[str, Any]]:
    """Run the Node client until it has ``count`` messages of every topic; its JSON lines
    (``offer``: the subprotocols it offers, comma-separated; both names by default)."""
    assert NODE is not None, "no node: `make deps` installs it"
    env = {**os.environ, "SUBPROTOCOLS": offer} if offer else None
    process = await asyncio.create_subprocess_exec(
        NODE,
        str(CLIENT / "subscribe.cjs"),
        f"ws://127.0.0.1:{port}",
        str(count),
        *topics,
        cwd=CLIENT,
        env=env,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    try:
        out, err = await asyncio.wait_for(process.communicate(), 60)
    except TimeoutError:
        process.terminate()  # the client says what it still misses
        _out, err = await process.communicate()
        raise AssertionError(f"the client timed out: {err.decode()[-1500:]}") from None
    finally:
        if process.returncode is None:
            process.kill()
            await process.wait()
    assert process.returncode == 0, err.decode()
    return [json.loads(line) for line in out.decode().splitlines() if line.strip()]
