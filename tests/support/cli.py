"""The station's command line, run in-process against a test's station daemon."""

from __future__ import annotations

import asyncio
import contextlib
import io

from stationd import cli
from stationd.daemon import StationDaemon


async def run_cli(station: StationDaemon, *argv: str) -> tuple[int, str, str]:
    """Run ``brasidas-station`` in a thread (it has its own event loop) against ``station``'s
    local API: exit code, stdout, stderr."""
    out, err = io.StringIO(), io.StringIO()
    api = ["--set", f"station.api_port={station.api_port}"]

    def call() -> int:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            return cli.main([*argv, *api])

    code = await asyncio.to_thread(call)
    return code, out.getvalue(), err.getvalue()
