"""The platform's recorder actor, found among a daemon's actors."""

from __future__ import annotations

from platformd.app import PlatformDaemon
from platformd.recorder import PlatformRecorder


def recorder_of(daemon: PlatformDaemon) -> PlatformRecorder:
    (recorder,) = [a for a in daemon.supervisor.actors if isinstance(a, PlatformRecorder)]
    return recorder
