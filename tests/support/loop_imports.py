"""Run as a script, in a fresh interpreter: ``loop_imports.py platform|station SETTING...``.

Starts the daemon with ``SECTION.KEY=VALUE`` settings, waits until it is in service (the
platform: armable and its NavCam playing, started as a station would if the recorder did not),
stops it, and prints as JSON every module looked
for on the event loop's thread once the daemon's first actor had started: each one blocked
the loop (tests/test_loop_imports.py).
"""

from __future__ import annotations

import asyncio
import importlib.abc
import importlib.machinery
import json
import os
import sys
import threading
from collections.abc import Sequence
from types import ModuleType

from brasidas.actor import Actor, Supervisor
from brasidas.config import PlatformConfig, StationConfig, load_config


class LoopImports(importlib.abc.MetaPathFinder):
    """First on ``sys.meta_path``: notes each module looked for (none already imported is)."""

    def __init__(self) -> None:
        self.loop_thread: int | None = None
        self.actors_running = False
        self.found: list[str] = []
        """Modules looked for on the loop's thread while the daemon's actors ran."""

    def find_spec(
        self, fullname: str, path: Sequence[str] | None, target: ModuleType | None = None
    ) -> importlib.machinery.ModuleSpec | None:
        if self.actors_running and threading.get_ident() == self.loop_thread:
            self.found.append(fullname)
        return None  # the finders after this one import it


async def until(predicate: object, timeout: float = 30.0) -> None:
    async def poll() -> None:
        while not callable(predicate) or not predicate():
            await asyncio.sleep(0.02)

    await asyncio.wait_for(poll(), timeout)


async def main(kind: str, settings: list[str], recorder: LoopImports) -> None:
    recorder.loop_thread = threading.get_ident()
    key = os.urandom(32)
    if kind == "platform":
        from platformd.app import PlatformDaemon

        platform = PlatformDaemon(load_config(PlatformConfig, None, settings), key)
        try:
            await platform.start()
            arming, media = platform.ctx.arming, platform.ctx.media
            assert arming is not None and media is not None
            await until(lambda: not arming.reasons())
            navcam = media.streams.get("navcam")
            if navcam is not None:
                if navcam.state.value != "playing" and not navcam.wanted.value == "playing":
                    # Not the recorder's (switched off): a station's first stream starts it.
                    await media.start_stream("navcam", "127.0.0.1", 9)
                await until(lambda: navcam.state.value == "playing")
        finally:
            await platform.stop()
    else:
        from stationd.daemon import StationDaemon

        station = StationDaemon(load_config(StationConfig, None, settings), key)
        try:
            await station.start()
        finally:
            await station.stop()


def run(argv: list[str]) -> None:
    recorder = LoopImports()
    sys.meta_path.insert(0, recorder)
    start = Supervisor.start

    def started(self: Supervisor, actor: Actor) -> None:
        recorder.actors_running = True
        start(self, actor)

    Supervisor.start = started  # type: ignore[method-assign]
    asyncio.run(main(argv[0], argv[1:], recorder))
    print(json.dumps({"on_the_loop": recorder.found}))


if __name__ == "__main__":
    run(sys.argv[1:])
