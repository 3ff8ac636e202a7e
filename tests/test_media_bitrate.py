"""The NavCam's bitrate follows the receivers' reported loss, within its bounds (sans-IO)."""

from __future__ import annotations

import itertools
import random

from brasidas.media.bitrate import (
    DRAIN_PAUSE_S,
    PACER_BACKLOG_S,
    STEP_S,
    TRANSPORT_WINDOW_S,
    BitrateController,
    FrameBudget,
    ResolutionChoice,
    TransportReport,
    frame_thinning,
)

READ_S = 0.1
"""The measured windows below were read this far apart (the sender reads every 50 ms: each
read then adds half as much of a window's growth)."""


_SEQUENCES = itertools.count(1000, 1000)


def _report_loss(controller: BitrateController, share: float, at: float, packets: int = 20) -> None:
    """Receiver reports at ``at`` and 40 ms before: ``share`` of ``packets`` lost between."""
    base = next(_SEQUENCES)
    controller.note_report(1, base, 0, at - 0.04)
    controller.note_report(1, base + packets, round(packets * share), at)


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


def _window(sent: float, received: float, growth_ms: float) -> TransportReport:
    """A transport-feedback window whose delay grew ``growth_ms`` across it."""
    packets = sent * 1000 * TRANSPORT_WINDOW_S / (8 * 1200)
    return TransportReport(sent, received, delay_trend_ms=growth_ms / packets)


def _clean_windows(
    controller: BitrateController,
    sent: float,
    received: float,
    count: int,
    every: float,
    start: float = 0.0,
) -> float:
    """``count`` windows of a link without a queue, one every ``every`` s: the next time."""
    now = start
    for _ in range(count):
        controller.on_transport(_window(sent, received, 0.0), sent, now)
        now += every
    return now


def test_a_queue_building_cuts_the_bitrate_to_under_what_arrived_at_once() -> None:
    controller = BitrateController(1500, 150)
    now = 0.0
    for _ in range(10):  # a clean link: no queue, nothing to cut
        assert controller.on_transport(_window(1500, 1490, 3.0), 1500, now) is None
        now += READ_S
    # 2 Mbit/s → 500 kbit/s: the windows after the drop, as measured (+56, +105, +256 ms).
    controller.on_transport(_window(1470, 977, 56.0), 1500, now)
    _report_loss(controller, 0.5, now + 0.09)  # the receivers count half the packets lost
    kbps = controller.on_transport(_window(1870, 640, 105.0), 1500, now + 0.1)
    # The first window still counts what arrived before the drop: far below what arrived,
    # and no frame while the queue drains (the sender pauses).
    assert kbps == 450
    assert controller.paused_at == now + 0.1
    assert controller.retransmissions_paused(now + 0.1 + DRAIN_PAUSE_S / 2)
    kbps = controller.on_transport(_window(2080, 357, 256.0), 1500, now + 0.2)
    assert kbps is not None
    assert kbps < 450  # under what the link carries (the lagging window goes on cutting)
    assert controller.overuses >= 1
    # After the pause, packets are sent again (those from before it: the sender's filter).
    assert not controller.retransmissions_paused(now + 0.15 + DRAIN_PAUSE_S)
    # Receiver reports counting the drop's losses afterwards do not cut it a second time, and
    # the bitrate does not climb back into the queue while it drains.
    held = controller.effective_kbps(1500)
    for step in range(1, 15):
        growth = -40.0 if step < 4 else 0.0  # the queue drains (-84, -48, -34 ms measured)
        at = now + 0.2 + step * 0.1
        controller.on_transport(_window(held, held, growth), 1500, at)
        assert controller.update(0.5, 1500, at) is None
    assert controller.effective_kbps(1500) == held


def test_random_loss_without_a_queue_never_lowers_the_bitrate() -> None:
    controller = BitrateController(1500, 150)
    now = 0.0
    for step in range(100):
        # 10 % lost at random, the delay flat but jittery (±20 ms a window, as measured).
        growth = 20.0 if step % 2 else -20.0
        controller.on_transport(_window(1500, 1350, growth), 1500, now)
        controller.update(0.40 if step % 7 == 0 else 0.10, 1500, now)  # a report spikes
        now += READ_S
    assert controller.effective_kbps(1500) == 1500
    assert controller.overuses == 0
    assert controller.collapsed_at is None


def test_a_cut_link_a_restarting_receiver_or_a_paused_forwarder_is_not_a_capacity() -> None:
    controller = BitrateController(1500, 150)
    # A forwarder paused 100 ms (a loaded machine) then caught up: the delay grew, but the
    # link delivered what was sent.
    for step in range(5):
        assert controller.on_transport(_window(1500, 1400, 100.0), 1500, step * 0.1) is None
    # ... or paused once, then its backlog arrived at once: one window, then a falling delay.
    assert controller.on_transport(_window(1500, 1000, 100.0), 1500, 0.6) is None
    assert controller.on_transport(_window(1500, 1600, -90.0), 1500, 0.7) is None
    # A window where nothing arrived (the delta of deltas is meaningless: -50 ms measured).
    assert controller.on_transport(TransportReport(1500, 0.0, -50.0), 1500, 0.8) is None
    assert controller.on_transport(TransportReport(1500, 0.0, 50.0), 1500, 0.9) is None
    assert controller.effective_kbps(1500) == 1500


def test_after_a_wrong_cut_the_bitrate_climbs_back_on_a_lossy_but_unqueued_link() -> None:
    controller = BitrateController(1500, 150)
    # A forwarder's long pause read as a queue that delivered 1100 of 1500 kbit/s.
    controller.on_transport(_window(1500, 1100, 60.0), 1500, 0.0)
    controller.on_transport(_window(1500, 1100, 60.0), 1500, 0.1)
    low = controller.effective_kbps(1500)
    assert low < 1000
    now = 0.2
    for _ in range(50):  # 5 s of a link losing 10 % at random, no queue
        controller.on_transport(_window(low, low * 0.9, 0.0), 1500, now)
        controller.update(0.10, 1500, now)
        now += READ_S
    # Back to under what it delivered (random loss alone cannot tell a full queue's).
    assert controller.effective_kbps(1500) >= 0.9 * 1100 - 1
    # A clean link: the rest of the way.
    for _ in range(200):
        controller.on_transport(_window(low, low, 0.0), 1500, now)
        controller.update(0.0, 1500, now)
        now += READ_S
    assert controller.effective_kbps(1500) == 1500


def test_without_transport_feedback_the_reported_loss_still_decides() -> None:
    controller = BitrateController(1500, 150)
    _steps(controller, 0.66, 4, 0.0)
    assert controller.effective_kbps(1500) < 500
    # Transport feedback that stopped a while ago no longer silences the reports.
    controller = BitrateController(1500, 150)
    controller.on_transport(_window(1500, 1500, 0.0), 1500, 0.0)
    _steps(controller, 0.66, 4, 0.0 + 1.0 + STEP_S)
    assert controller.effective_kbps(1500) < 500


def test_after_a_capacity_drop_the_bitrate_stays_under_it_and_climbs_only_on_a_clean_link() -> None:
    controller = BitrateController(1500, 150)
    now = 0.0
    for received in (977.0, 640.0, 450.0):  # the drop to 500 kbit/s, as measured
        controller.on_transport(_window(1600, received, 120.0), 1500, now)
        now += READ_S
    assert controller.capacity_kbps == 450.0  # what it delivered, by the newest window
    for _ in range(60):  # 6 s: no queue, no loss
        controller.on_transport(_window(400, 400, 0.0), 1500, now)
        controller.update(0.0, 1500, now)
        now += READ_S
    # It climbed, but not back into the queue it just left.
    assert 0.85 * 450 < controller.effective_kbps(1500) <= 0.9 * 450
    # Behind a full queue the delay stops growing but the loss shows: no climbing on it.
    held = controller.target_kbps
    for _ in range(150):  # 15 s, past the capacity's memory
        controller.on_transport(_window(held, held * 0.93, 0.0), 1500, now)
        controller.update(0.07, 1500, now)
        now += READ_S
    assert controller.target_kbps == held


def test_the_picture_is_halved_below_its_bits_and_restored_above_with_hysteresis() -> None:
    choice = ResolutionChoice()
    assert choice.size(640, 480) == (640, 480)
    assert not choice.update(1500, 640, 480, 30, 0.0)  # 0.16 bits a pixel
    assert choice.update(400, 640, 480, 30, 1.0)  # 0.043: smeared, large frames
    assert choice.size(640, 480) == (320, 240)
    # Held a while (each change costs a keyframe), and not restored just above the limit.
    assert not choice.update(1500, 640, 480, 30, 2.0)
    assert not choice.update(600, 640, 480, 30, 10.0)  # 0.065: between the two limits
    assert choice.update(800, 640, 480, 30, 11.0)  # 0.087
    assert choice.size(640, 480) == (640, 480)
    # 5 fps needs a sixth of the bits for the same picture.
    assert not ResolutionChoice().update(250, 640, 480, 5, 0.0)


def test_a_capacity_drop_confirmed_by_a_report_losing_most_packets_pauses_at_the_first_window() -> (
    None
):
    controller = BitrateController(1500, 150)
    # The first window after a drop to 500 kbit/s (measured: +15 ms, 72 % delivered) and the
    # receiver report just before it losing 46 %: the queue overflows, cut and pause at once.
    _report_loss(controller, 0.46, 0.19)
    assert controller.on_transport(_window(1460, 1050, 15.0), 1500, 0.2) is not None
    assert controller.paused_at == 0.2
    # The next windows still show the overflow (they reach back 300 ms): no second pause.
    controller.on_transport(_window(1820, 450, 60.0), 1500, 0.3)
    controller.on_transport(_window(1800, 400, 60.0), 1500, 0.4)
    assert controller.paused_at == 0.2
    assert controller.effective_kbps(1500) < 500
    # A second overuse a while later (the feedback coming all along) is a new drop: a new
    # pause.
    for step in range(5, 20):
        controller.on_transport(_window(450, 450, 0.0), 1500, step * READ_S)
    _report_loss(controller, 0.5, 2.0)
    controller.on_transport(_window(450, 200, 40.0), 1500, 2.0)
    assert controller.paused_at == 2.0


def test_without_a_lossy_report_one_window_is_not_enough_and_random_loss_never_pauses() -> None:
    controller = BitrateController(1500, 150)
    # A forwarder's pause: the delay grew in one window, no report counted a loss.
    _report_loss(controller, 0.0, 0.19)
    assert controller.on_transport(_window(1500, 1000, 40.0), 1500, 0.2) is None
    assert controller.paused_at is None
    # A report of a stale loss (older than a window) does not confirm either.
    controller = BitrateController(1500, 150)
    _report_loss(controller, 0.6, 0.0)
    assert controller.on_transport(_window(1500, 1000, 40.0), 1500, 0.5) is None
    # 10 % random loss with spiking reports, read as often as the sender does: no queue, so
    # no pause (nor cut).
    # Reports every 20 ms of 3 packets each (30 fps); at 5 fps of one packet or none, a lost
    # one reading 100 %: the share counts only over 10 packets or more.
    for packets_per_report in (3, 1):
        controller = BitrateController(1500, 150)
        rng = random.Random(7)
        highest = lost = 0
        now = 0.0
        for step in range(600):
            highest += packets_per_report
            lost += sum(rng.random() < 0.1 for _ in range(packets_per_report))
            controller.note_report(1, highest, lost, now)
            if step % 2:
                growth = 20.0 if step % 4 == 1 else -20.0
                controller.on_transport(_window(1500, 1350, growth), 1500, now)
                controller.confirm_pending(1500, now)
            now += 0.02
        assert controller.paused_at is None
        assert controller.effective_kbps(1500) == 1500
    # Every packet of several reports lost, but 7 packets in all: not enough to confirm.
    controller = BitrateController(1500, 150)
    for step in range(8):
        controller.note_report(1, step, step, step * 0.02)
    assert not controller.on_transport(_window(1460, 975, 15.0), 1500, 0.16)


def test_the_frame_budget_skips_frames_while_a_pause_lasts_and_then_holds_the_bitrate() -> None:
    budget = FrameBudget(1500)
    now = 0.0
    # A link that keeps up: 6 kB frames at 1.5 Mbit/s, a 10 kB keyframe each second: never skipped.
    for frame in range(90):
        assert budget.admit(now)
        budget.on_encoded(10_000 if frame % 30 == 0 else 6000, now)
        now += 1 / 30
    assert budget.skipped == 0
    # The link over its capacity: nothing is encoded while its queue drains (what was
    # encoded before, counted at the lowered bitrate, does not hold the frames after it)...
    budget.on_encoded(60_000, now)
    budget.set_rate(400, now)
    budget.pause(DRAIN_PAUSE_S, now)
    start = now
    admitted = []
    for _ in range(60):  # 2 s of frames from the camera
        if budget.admit(now):
            admitted.append(now)
            # ... then the encoder's frames stay large for a while after the cut (6 kB).
            budget.on_encoded(6000, now)
        now += 1 / 30
    assert admitted[0] >= start + DRAIN_PAUSE_S
    assert admitted[0] < start + DRAIN_PAUSE_S + 0.05  # the first frame after it goes
    # What was encoded over the 2 s stays within the target (400 kbit/s) plus the allowance.
    sent_bits = 6000 * 8 * len(admitted)
    assert sent_bits <= 400_000 * (now - start) + 400_000 * PACER_BACKLOG_S + 6000 * 8
    assert budget.skipped > 0


def test_the_frame_budget_never_skips_away_from_a_capacity_drop() -> None:
    # 5 fps: a keyframe's burst is many times the bitrate's share of a frame interval; with
    # no link over its capacity lately, the next frame still goes.
    budget = FrameBudget(250)
    budget.on_encoded(20_000, 0.0)
    assert budget.admit(0.2)
    assert budget.skipped == 0


def test_a_retransmission_from_before_the_pause_is_told_from_one_after_it() -> None:
    from brasidas.media.video import _sent_before

    def rtx(original: int, extension_words: int) -> bytes:
        # RTP header (with or without the one-byte header extensions the sender adds), then
        # the original sequence number (RFC 4588).
        first = 0x90 if extension_words else 0x80
        header = bytes([first, 97, 0, 1]) + bytes(8)
        if extension_words:
            header += b"\xbe\xde" + extension_words.to_bytes(2, "big") + bytes(4 * extension_words)
        return header + original.to_bytes(2, "big") + b"payload"

    for words in (0, 3):
        assert _sent_before(rtx(1000, words), 1001)
        assert not _sent_before(rtx(1001, words), 1001)  # the keyframe's own: sent again
        assert _sent_before(rtx(65530, words), 5)  # across the sequence's wrap
        assert not _sent_before(rtx(7, words), 5)


def test_a_lossy_report_just_after_a_window_that_showed_the_queue_confirms_it_at_once() -> None:
    # As measured: a window at +0.14 s showed a 32 ms queue delivering 67 % (one read: not
    # yet enough), the receiver report 20 ms later lost 71 %, the next window came 45 ms on.
    controller = BitrateController(1500, 150)
    assert controller.on_transport(_window(1460, 975, 45.0), 1500, 0.14) is None
    assert controller.confirm_pending(1500, 0.15) is None  # no lossy report yet
    _report_loss(controller, 0.71, 0.165)
    assert controller.confirm_pending(1500, 0.165) == 450
    assert controller.paused_at == 0.165
    assert controller.confirm_pending(1500, 0.17) is None  # once
    # A lossy report long after the window (0.1 s or more) confirms nothing.
    controller = BitrateController(1500, 150)
    controller.on_transport(_window(1460, 975, 45.0), 1500, 0.14)
    _report_loss(controller, 0.71, 0.3)
    assert controller.confirm_pending(1500, 0.3) is None
    # Nor a report with a mesh's random loss.
    controller = BitrateController(1500, 150)
    controller.on_transport(_window(1460, 975, 45.0), 1500, 0.14)
    _report_loss(controller, 0.2, 0.16)
    assert controller.confirm_pending(1500, 0.16) is None
    assert controller.paused_at is None


def test_an_overuse_no_receiver_report_confirms_pauses_but_cuts_only_to_what_arrived() -> None:
    # Two windows of a growing queue without loss counted (a loaded forwarder's stall, or a
    # 5 fps stream's reports too few packets to count): the pause costs a frame or two, a
    # cut to 0.3x would cost seconds of a crushed bitrate.
    controller = BitrateController(1500, 150)
    controller.on_transport(_window(1500, 1000, 60.0), 1500, 0.0)
    assert controller.on_transport(_window(1500, 1000, 60.0), 1500, 0.1) == 850
    assert controller.paused_at == 0.1


def test_a_queue_seen_packet_by_packet_pauses_cuts_once_and_ignores_what_was_sent_before() -> None:
    controller = BitrateController(1500, 150)
    # A queue drained at a quarter of what is sent: pause, the deep cut at once.
    kbps = controller.on_queue(1600, 400, 1500, 10.0, sent_at=9.99)
    assert controller.paused_at == 10.0
    assert kbps == 450
    # The next feedbacks still report packets sent before that cut: no second cut.
    assert controller.on_queue(1600, 300, 1500, 10.03, sent_at=9.995) is None
    assert controller.queue_overuses == 1
    # A packet sent after it still queueing: cut again, toward what the link delivers.
    assert controller.on_queue(600, 300, 1500, 10.3, sent_at=10.2) is not None
    assert controller.effective_kbps(1500) == 255
    assert controller.pauses == 1


BLACKOUT_WINDOWS = [
    # (s after the first, sent kbit/s, received kbit/s, delay trend ms) read by the sender
    # around a 300 ms link cut at 0.346-0.646 s (fps30_burst300ms, recorded).
    (0.000, 1353.1, 1356.2, -0.003),
    (0.033, 1504.4, 1503.5, 0.027),
    (0.066, 1367.7, 1370.3, 0.001),
    (0.099, 1502.4, 1502.5, -0.010),
    (0.132, 1502.1, 1502.1, -0.005),
    (0.166, 1504.6, 1504.7, 0.002),
    (0.199, 1379.6, 1384.3, -0.014),
    (0.233, 1367.6, 1371.1, 0.002),
    (0.267, 1505.9, 1504.9, -0.010),
    (0.299, 1505.0, 1504.1, 0.037),
    (0.333, 1504.4, 1505.2, -0.027),
    # The feedback comes back: the first window spans the silence.
    (0.667, 3005.5, 1294.7, 0.976),
    (0.673, 1416.0, 212.7, 0.048),
    (0.699, 1517.8, 442.7, 0.072),
    (0.833, 1203.2, 411.6, 0.025),
    (0.932, 1028.6, 362.3, 0.035),
    (1.032, 1501.0, 1500.0, 0.001),
]
BLACKOUT_REPORT_AT = 0.699
"""A receiver report counting 58 of the 80 packets since its last lost (the cut's)."""
BLACKOUT_PACKET_QUEUE_MS = {0.299: 77.5, 0.667: 104.7, 0.673: 5.0, 0.699: 7.3}
"""The per-packet feedback's newest wait just before these windows (recorded at cuts: a loaded
machine's lone spike, then the first after the cut counts a packet the relay held across it);
1 ms before the others."""


def test_a_link_cut_and_its_lost_packets_are_not_an_overuse() -> None:
    controller = BitrateController(1500, 150)
    for at, sent, received, trend in BLACKOUT_WINDOWS:
        controller.note_queue(BLACKOUT_PACKET_QUEUE_MS.get(at, 1.0))
        if at == BLACKOUT_REPORT_AT:
            controller.note_report(1, 5000, 100, at - 0.03)
            controller.note_report(1, 5080, 158, at)
        controller.on_transport(TransportReport(sent, received, trend), 1500, at)
        controller.confirm_pending(1500, at)
        controller.update(0.7 if at > 0.6 else 0.0, 1500, at)
    # The old reading: +92 ms of "queue" across the gap, confirmed by the report: three cuts
    # to 350 kbit/s and a drain pause.
    assert controller.overuses == 0
    assert controller.paused_at is None
    assert controller.effective_kbps(1500) == 1500
    assert controller.silences == 1
    # A real capacity drop after it, the feedback coming all along, is still cut at once.
    now = _clean_windows(controller, 1500, 1495, 5, 0.033, start=1.065) - 0.033
    controller.on_transport(_window(1470, 977, 56.0), 1500, now + 0.033)
    _report_loss(controller, 0.5, now + 0.06)
    assert controller.on_transport(_window(1870, 640, 105.0), 1500, now + 0.066) is not None
    assert controller.paused_at == now + 0.066


def test_slow_feedback_is_learned_as_usual_not_read_as_silences() -> None:
    # At a low bitrate the receivers' feedback comes every ~100-250 ms: after the first few,
    # no silence, and a capacity drop there is still seen.
    controller = BitrateController(300, 100)
    now = _clean_windows(controller, 300, 300, 20, 0.25)
    silences = controller.silences
    controller.on_transport(_window(300, 200, 40.0), 300, now)
    _report_loss(controller, 0.5, now + 0.2)
    assert controller.on_transport(_window(300, 150, 60.0), 300, now + 0.25) is not None
    assert controller.silences == silences


def test_the_feedback_silent_through_a_drain_pause_still_cuts_on() -> None:
    # The encoder sent nothing for the pause, so no feedback came: not a link cut, and the
    # lagging windows after it go on cutting while the queue still grows.
    controller = BitrateController(1500, 150)
    now = _clean_windows(controller, 1500, 1490, 10, 0.033)
    _report_loss(controller, 0.5, now)
    # (Read every 33 ms, a window adds a ninth of its growth.)
    assert controller.on_transport(_window(1470, 977, 300.0), 1500, now) is not None
    assert controller.paused_at == now
    cut = controller.effective_kbps(1500)
    controller.on_transport(_window(1870, 357, 256.0), 1500, now + 0.2)
    assert controller.silences == 0
    assert controller.effective_kbps(1500) < cut


def test_a_queue_seen_packet_by_packet_just_after_a_silence_lets_the_windows_cut_on() -> None:
    # A loaded machine's stall (0.2 s without feedback), then a capacity drop the per-packet
    # feedback sees at once: the windows after it are the drop's, and confirm it.
    controller = BitrateController(1500, 150)
    now = _clean_windows(controller, 1500, 1490, 10, 0.033) + 0.2
    controller.on_transport(_window(1500, 1400, 0.0), 1500, now)
    assert controller.silences == 1
    assert controller.on_queue(1600, 500, 1500, now + 0.03, sent_at=now) is not None
    _report_loss(controller, 0.5, now + 0.06)
    controller.on_transport(_window(1470, 700, 300.0), 1500, now + 0.066)
    assert controller.overuses == 2
    assert controller.collapsed_at == now + 0.066


def test_a_capacity_drop_that_holds_its_feedback_back_is_cut_at_the_first_window_after() -> None:
    # 2 Mbit/s → 500 kbit/s: the per-packet feedback reads the queue building (21, 45 ms),
    # then the capped return link holds the feedback back 0.25 s (measured 0.05-0.6 s). The
    # window after it is the queue's, confirmed by the receivers' loss: pause and cut at once,
    # not set aside as a link cut's until the per-packet path confirms it later.
    controller = BitrateController(1500, 150)
    now = 0.0
    for _ in range(20):
        controller.note_queue(1.0)
        controller.on_transport(_window(1500, 1490, 0.0), 1500, now)
        now += 0.025
    controller.note_queue(21.0)
    assert controller.on_transport(_window(1450, 1300, 15.0), 1500, now + 0.03) is None
    controller.note_queue(45.0)
    assert controller.on_transport(_window(1450, 1150, 25.0), 1500, now + 0.06) is None
    stalled_until = now + 0.31
    controller.note_queue(150.0)
    _report_loss(controller, 0.5, stalled_until - 0.01)
    kbps = controller.on_transport(_window(1450, 500, 120.0), 1500, stalled_until)
    assert kbps is not None and kbps <= 450
    assert controller.paused_at == stalled_until
    assert (controller.silences, controller.queue_stalls) == (0, 1)


POLL_S = 0.05
"""The sender's look at the feedback (:data:`~brasidas.media.bitrate.TRANSPORT_POLL_S`)."""


def _cut_link(controller: BitrateController, start: float, seconds: float) -> float:
    """A running 1500 kbit/s link (windows every 30 ms, a clean receiver report every 0.5 s),
    then cut both ways for ``seconds``: the sender's polls find nothing. The time it returns."""
    now = start
    while now < start + 2.0:
        controller.on_transport(_window(1500, 1495, 0.0), 1500, now)
        report = round((now - start) / 0.03) % 17 == 0
        controller.update(0.0 if report else None, 1500, now)
        now += 0.03
    for _ in range(round(seconds / POLL_S)):
        controller.update(None, 1500, now)
        now += POLL_S
    return now


def test_a_receiver_report_across_a_long_cut_counts_the_cuts_loss_not_congestion() -> None:
    # Back after 1.5 s (older than the feedback's freshness), the report first: it counts
    # 94 % of the packets since the last lost (recorded), all of them the cut's.
    controller = BitrateController(1500, 150)
    now = _cut_link(controller, 0.0, 1.5)
    assert controller.update(0.94, 1500, now + 0.01) is None
    _clean_windows(controller, 1500, 1495, 10, 0.03, start=now + 0.04)
    # The old reading: a collapse, 1500 → 150 kbit/s (the floor) on an unchanged link.
    assert controller.effective_kbps(1500) == 1500
    assert (controller.silences, controller.cut_reports) == (1, 1)
    # The feedback first, the report 30 ms on: not smoothed in either (the old code held
    # 47 % of "loss" for the next report: FEC up, no climbing).
    now = _cut_link(controller, now + 0.4, 1.5)
    _clean_windows(controller, 1500, 1495, 2, 0.03, start=now + 0.01)
    controller.update(0.94, 1500, now + 0.04)
    assert controller.loss == 0.0
    assert controller.cut_reports == 2
    # The link back with a quarter of its capacity: the windows still cut at once, and the
    # next report's loss counts again.
    now = _clean_windows(controller, 1500, 1495, 10, 0.03, start=now + 0.07) - 0.03
    controller.on_transport(_window(1470, 977, 56.0), 1500, now + 0.033)
    _report_loss(controller, 0.5, now + 0.06)
    assert controller.on_transport(_window(1870, 640, 105.0), 1500, now + 0.066) is not None
    controller.update(0.5, 1500, now + 0.07)
    assert controller.loss == 0.25
    assert controller.effective_kbps(1500) <= 500


def test_reports_that_keep_coming_through_a_feedback_silence_still_decide() -> None:
    # The feedback stops (a receiver without it now), the reports go on: the loss decides.
    controller = BitrateController(1500, 150)
    now = _clean_windows(controller, 1500, 1495, 10, 0.03)
    for _ in range(8):
        controller.update(0.0, 1500, now)
        now += STEP_S / 2
    _steps(controller, 0.66, 3, now)
    # (At most the first after the feedback stopped is set aside: its interval holds the
    # silence's start, which a cut's does too.)
    assert controller.cut_reports <= 1
    assert controller.effective_kbps(1500) < 500
