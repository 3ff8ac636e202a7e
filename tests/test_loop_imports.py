"""No import on the event loop once a daemon's actors run (brasidas.subsystems).

An import blocks the loop, for tenths of a second each on a loaded machine where no bytecode
is cached: the motor driver's first probe timed out behind the subsystems set up after it
(w11-dropout). Each daemon runs in a fresh interpreter (tests/support/loop_imports.py), with
what its configuration can switch on switched on, and reports every module looked for on the
loop's thread after its first actor started.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

from brasidas import subsystems
from brasidas.config import PlatformConfig, load_config

SCRIPT = Path(__file__).parent / "support" / "loop_imports.py"

PLATFORM = (
    "sim.enabled=true",
    "signaling.port=0",
    "velocity.port=0",
    "beacon.enabled=false",
    "mavlink.enabled=true",
    "lidar.enabled=true",
    'payload.enabled=["turret"]',
)
STATION = (
    "station.api_port=0",
    "discovery.port=0",
    "discovery.bind_host=127.0.0.1",
    "foxglove.port=0",
)


def imports_on_the_loop(kind: str, settings: tuple[str, ...], state: Path) -> list[str]:
    # -P: the script's folder is not put on sys.path (tests/support/foxglove.py would hide
    # the Foxglove SDK).
    done = subprocess.run(
        [sys.executable, "-P", str(SCRIPT), kind, *settings],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "XDG_STATE_HOME": str(state)},
        check=False,
    )
    assert done.returncode == 0, f"the {kind} did not run:\n{done.stderr[-3000:]}"
    found: list[str] = json.loads(done.stdout.splitlines()[-1])["on_the_loop"]
    return found


@pytest.mark.parametrize(
    ("kind", "settings"),
    [
        ("platform", PLATFORM),
        # No recorder: GStreamer is first needed when a station starts the NavCam.
        ("platform", (*PLATFORM, "recorder.enabled=false")),
        ("station", STATION),
    ],
    ids=["platform", "platform-first-stream", "station"],
)
def test_nothing_is_imported_on_the_loop_once_actors_run(
    kind: str, settings: tuple[str, ...], tmp_path: Path
) -> None:
    assert imports_on_the_loop(kind, settings, tmp_path / "state") == []


def test_modules_load_in_order_and_preload_what_the_config_enables(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    config = load_config(PlatformConfig, None, [])
    seen: list[tuple[str, object]] = []
    first, second = ModuleType("first"), ModuleType("second")
    first.preload = lambda given: seen.append(("first", given))  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "first", first)
    monkeypatch.setitem(sys.modules, "second", second)  # no preload: nothing to import later
    assert subsystems.load(["second", "first"], config) == (second, first)
    assert seen == [("first", config)]
