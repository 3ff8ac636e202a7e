"""What the CLI prints in words (issue 31, item 9): `logs` lists a recording's channels under
it, wrapped (32 names on one line ran off the terminal); `status` says no *other* platform's
beacon was heard, not "platforms none heard" while connected."""

from __future__ import annotations

from brasidas.codecs.telemetry_schema import Platforms
from stationd.cli import _describe_recordings
from stationd.status_view import _platforms


def test_logs_wraps_a_recordings_channels_under_it() -> None:
    channels = {f"/telemetry/section_{index:02d}": {} for index in range(32)}
    text = _describe_recordings(
        {
            "recording": True,
            "recordings": [
                {"name": "a.mcap", "start": 0, "duration_s": 9.0, "size": 1e6, "channels": channels}
            ],
        }
    )
    lines = text.splitlines()
    assert lines[1].startswith("a.mcap")
    assert lines[1].endswith("32 channels")
    wrapped = lines[2:]
    assert len(wrapped) > 3
    assert all(len(line) <= 100 for line in wrapped)
    assert all(line.startswith("    ") for line in wrapped)
    assert sum(line.count("/telemetry/") for line in wrapped) == 32


def test_status_says_whose_beacons_were_not_heard() -> None:
    assert _platforms(Platforms(age_s={})) == "no other platform's beacon heard"
    assert _platforms(Platforms(age_s={"rover-2": 3.0})) == "rover-2 (3 s ago)"
