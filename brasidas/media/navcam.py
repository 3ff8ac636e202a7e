"""NavCam policy, sans-IO: its sender settings from config, and its framerate by mode.

The seed ran the NavCam at 5 fps for monitoring and 30 fps while the operator drives (manual
override engaged, ch. 10 §3.2); command 10.5 sets the framerate of the current mode.
"""

from __future__ import annotations

from typing import Any

from brasidas.config import NavCamSection
from brasidas.media.video import VideoSettings


def navcam_settings(navcam: NavCamSection, *, sim: bool) -> VideoSettings:
    """Sender settings: the configured camera, or in sim a live test source."""
    return VideoSettings(
        width=navcam.width,
        height=navcam.height,
        camera_framerate=navcam.framerate,
        framerate=max(1, min(navcam.idle_framerate, navcam.framerate)),
        bitrate_kbps=navcam.bitrate_kbps,
        device=navcam.device,
        source_format=navcam.format,
        test_source=sim,
        pattern=navcam.sim_pattern,
        motion=navcam.sim_motion,
        encoder=navcam.encoder,
        port=navcam.port,
        intra_refresh=navcam.intra_refresh,
        fec_max_percent=navcam.fec_max_percent,
    )


def parse_framerate(raw: Any, limit: int) -> int:
    """A 10.5 framerate value: an integer 1..``limit``; ValueError with the reason."""
    try:
        fps = int(str(raw).strip())
    except ValueError:
        raise ValueError(f"framerate must be an integer, not {raw!r}") from None
    if not 1 <= fps <= limit:
        raise ValueError(f"framerate must be 1-{limit} fps (camera rate), not {fps}")
    return fps


class FrameratePolicy:
    """The framerate wanted for each mode; ``current`` follows the manual override."""

    def __init__(self, *, engaged_fps: int, idle_fps: int, limit: int) -> None:
        self.limit = limit
        self.rates = {
            "engaged": max(1, min(engaged_fps, limit)),
            "idle": max(1, min(idle_fps, limit)),
        }
        self.engaged = False
        self.held: int | None = None
        """With the automatic switch off (10.9): the framerate kept whatever the mode."""

    @property
    def auto(self) -> bool:
        """The framerate follows the manual override (the automatic 5/30 fps switch)."""
        return self.held is None

    def set_auto(self, on: bool) -> int:
        """Switch the automatic framerate on (back to the mode's) or off (keep the current)."""
        self.held = None if on else self.current
        return self.current

    @property
    def mode(self) -> str:
        return "engaged" if self.engaged else "idle"

    @property
    def current(self) -> int:
        return self.held if self.held is not None else self.rates[self.mode]

    def set_override(self, engaged: bool) -> int:
        """The manual override changed; returns the framerate to use now."""
        self.engaged = engaged
        return self.current

    def set_current(self, raw: Any) -> int:
        """10.5: the framerate of the current mode (ValueError if invalid); returns it."""
        fps = parse_framerate(raw, self.limit)
        if self.held is not None:
            self.held = fps
        else:
            self.rates[self.mode] = fps
        return fps
