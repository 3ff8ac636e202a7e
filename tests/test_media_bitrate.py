"""The NavCam's bitrate follows the receivers' reported loss, within its bounds (sans-IO)."""

from __future__ import annotations

from brasidas.media.bitrate import STEP_S, BitrateController, frame_thinning


def _steps(controller: BitrateController, loss: float | None, count: int, start: float) -> float:
    now = start
    for _ in range(count):
        controller.update(loss, 1500, now)
        now += STEP_S
    return now


def test_congestion_lowers_the_bitrate_within_two_seconds_and_clean_reports_raise_it() -> None:
    controller = BitrateController(1500, 150)
    # A 500 kbit/s bottleneck under 1500 kbit/s: two thirds of the packets dropped.
    now = _steps(controller, 0.66, 4, 0.0)  # 2 s
    assert controller.effective_kbps(1500) < 500
    now = _steps(controller, 0.66, 40, now)
    assert controller.effective_kbps(1500) == 150  # never below the floor
    # Routine random loss that retransmission repairs (5 %) neither lowers nor raises it.
    held = controller.target_kbps
    now = _steps(controller, 0.05, 10, now)
    assert controller.target_kbps == held
    # A clean link: back up to the ceiling, never above it.
    _steps(controller, 0.0, 100, now)
    assert controller.target_kbps == 1500


def test_no_report_changes_nothing_and_steps_are_spaced() -> None:
    controller = BitrateController(1500, 150)
    assert controller.update(None, 1500, 0.0) is None
    assert controller.update(0.9, 1500, 0.1) is None  # within the step: smoothed only
    assert controller.update(0.9, 1500, 0.6) is not None
    assert controller.update(0.9, 1500, 0.7) is None  # decreases a quarter second apart
    # A lower framerate's ceiling bounds what the encoder gets, not the target kept for later.
    controller = BitrateController(1500, 150)
    assert controller.effective_kbps(250) == 250
    controller.update(0.0, 250, 1.0)
    assert controller.effective_kbps(1500) == 1500


def test_a_capacity_drop_lowers_the_bitrate_on_its_first_report() -> None:
    controller = BitrateController(1500, 150)
    _steps(controller, 0.0, 4, 0.0)
    # 2 Mbit/s → 500 kbit/s under 1500 kbit/s: two thirds lost in the first report. The
    # smoothed loss alone (0.33) would have lowered it to ~950 and needed two more steps.
    controller.update(0.66, 1500, 2.0)
    assert controller.effective_kbps(1500) < 500
    assert controller.collapsed_at is None  # one report: not yet a drop to thin frames for
    controller.update(0.15, 1500, 2.3)  # the queue still overflowing: confirmed
    assert controller.collapsed_at == 2.3
    # A mesh's random loss is not a collapse, even a report at 30 %: the smoothed loss
    # decides (1500 x 0.85 x 0.95), and frames are never thinned for it.
    controller = BitrateController(1500, 150)
    _steps(controller, 0.0, 4, 0.0)
    assert controller.update(0.30, 1500, 2.0) == 1211
    assert controller.collapsed_at is None


def test_a_bitrate_forced_far_down_sends_fewer_frames_within_bounds() -> None:
    assert frame_thinning(30, 1500, 1500) == 1
    assert frame_thinning(30, 700, 1500) == 2  # under half its share: 15 fps
    assert frame_thinning(30, 300, 1500) == 3  # under a quarter: 10 fps, the least
    assert frame_thinning(20, 150, 1000) == 2  # never below 10 fps
    assert frame_thinning(5, 150, 250) == 1  # monitoring rate: never thinned
