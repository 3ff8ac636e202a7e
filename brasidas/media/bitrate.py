"""A NavCam bitrate that follows the link, from the receivers' RTCP reports (sans-IO).

Loss-based, as the loss half of Google's congestion control: every :data:`STEP_S` the worst
receiver's smoothed fraction of packets lost (RTCP receiver reports, counted before repair:
the link's own loss) decides. Above :data:`CONGESTED_LOSS` the link is over its capacity (a
full queue drops the excess) and the bitrate falls to what got through, less 5 %; below
:data:`CLEAN_LOSS` it climbs back by :data:`CLIMB` a step toward the configured ceiling; in
between (a mesh's routine random loss, which retransmission repairs) it holds. Never below
``floor_kbps``, never above the ceiling the framerate allows.

Delay-based, as the delay half: the sender's rtpsession reads the receivers' transport-wide
feedback (TWCC: each packet's arrival time) into a :class:`TransportReport` per feedback
window: what was sent and what arrived in it, and how the one-way delay grew. A queue
building (the delay growing packet after packet) or a link delivering far less than was sent
is over its capacity: the bitrate falls at once to under what arrived, a round trip after the
queue started, where a receiver report counting the loss comes a second or two later.
Random loss neither grows the delay nor takes a quarter of the packets, so it never cuts.
"""

from __future__ import annotations

from dataclasses import dataclass

STEP_S = 0.5
CONGESTED_LOSS = 0.10
CLEAN_LOSS = 0.02
CLIMB = 1.08
SMOOTHING = 0.5
"""Weight of the newest report in the smoothed loss."""
COLLAPSE_LOSS = 0.35
"""A report losing more than this is a capacity drop, not a mesh's random loss (a single
report at 10 % random loss exceeded 20 % now and then, measured): the bitrate
falls on that report, to what got through, without waiting for the smoothing (measured at
2 Mbit/s → 500 kbit/s: smoothed alone, three steps and 1.5 s of a full queue dropping)."""
COLLAPSE_CONFIRM_S = 1.0
COLLAPSE_DELIVERED = 1 - COLLAPSE_LOSS
"""The same in transport feedback: a window delivering less than this share of what was sent."""
DECREASE_GAP_S = 0.25
"""Decreases no closer than this (a report or two apart)."""


@dataclass(frozen=True)
class TransportReport:
    """One window of transport-wide feedback (GStreamer rtpsession's ``twcc-stats``: the
    packets sent in the last :data:`TRANSPORT_WINDOW_S` whose fate the receiver reported)."""

    sent_kbps: float
    received_kbps: float
    """What arrived in the window, at the receiver's pace: a full link's capacity."""
    delay_trend_ms: float
    """Mean change of the one-way delay from one packet to the next (delta of deltas): > 0
    while a queue builds, about 0 on a link that keeps up, whatever it loses at random."""
    packet_bytes: int = 1200
    """The packets' usual size (the payloader's MTU), to count the window's packets."""

    @property
    def queue_growth_ms(self) -> float:
        """How much the one-way delay grew across the window (the trend times its packets)."""
        packets = self.sent_kbps * 1000 * TRANSPORT_WINDOW_S / (8 * self.packet_bytes)
        return self.delay_trend_ms * packets


TRANSPORT_WINDOW_S = 0.3
"""rtpsession's TWCC statistics window."""
TRANSPORT_POLL_S = 0.05
"""How often the sender looks at the feedback (each new window is read once; receivers send
it every ~30 ms: 0.1 s added 50 ms on average to seeing a capacity drop)."""
OVERUSE_QUEUE_MS = 20.0
"""A queue this long (estimated from the delay's growth, window after window) is a link over
its capacity: a keyframe's burst drains within a window, a mesh's random loss and jitter do
not grow it, a link a few percent over its capacity grows it steadily (measured windows on
a clean 2 Mbit/s link: within ±20 ms each; at a drop to 500 kbit/s: +56, then +133 ms)."""
OVERUSE_DELIVERED = 0.75
"""A queue over capacity delivers less than this share of what was sent (measured at the
drop to 500 kbit/s: 0.73, 0.48, 0.24 in the windows after it; at 10 % random loss ~0.9; a
forwarder's 50 ms pause ~0.86)."""
OVERUSE_READS = 2
"""Consecutive windows that must show the overuse, :data:`OVERUSE_SPAN_S` apart or more; one
when a receiver report just before it lost over :data:`COLLAPSE_LOSS` (a forwarder's pause
loses nothing)."""
OVERUSE_SPAN_S = 0.06
"""(A forwarder's stall shows in the windows of its feedback; its backlog, arriving at once,
in the next feedback, ~30 ms later. Read 0.1 s apart at each feedback, a drop waited ~90 ms
more, measured: 0.24 → 0.33 s.)"""
CONFIRM_PACKETS = 10
"""Receiver reports confirm an overuse only over this many packets or more (at 10 % random
loss 4 or more of 10 are lost about once in 80)..."""
CONFIRM_SPAN_S = 0.15
"""... reported within this long."""
CANDIDATE_S = 0.1
"""A window read this recently is confirmed by a lossy receiver report coming after it."""
CONFIRMED_QUEUE_SHARE = 0.5
"""With such a report, a queue estimated at this share of :data:`OVERUSE_QUEUE_MS` is enough."""
MOST_CUT = 0.5
"""One cut lowers the bitrate to no less than this share (a window's received rate can read
low; the next window cuts again if the queue still grows)."""
CAPACITY_MEMORY_S = 10.0
"""After the link was over its capacity, the bitrate climbs to no more than
:data:`CLIMB_UNDER` of what it delivered then, this long."""
CLIMB_UNDER = 0.9
CLIMB_TO_CAPACITY = 1.25
"""The climb a step while under :data:`CLIMB_UNDER` of that capacity."""
CLEAN_QUEUE_MS = 5.0
"""Under this estimated queue the bitrate may climb (whatever the random loss)."""
QUEUE_LEAK = 0.9
"""The estimate fades by this at each window read, so that measurement errors do not add up."""
OVERUSE_BACKOFF = 0.85
"""Over capacity, the bitrate falls to this share of what arrived: the queue drains."""
TRANSPORT_FRESH_S = 1.0
"""Transport feedback this recent decides decreases (receivers without it: the loss does). A
receiver report whose interval spans a link cut (:data:`SILENCE_S`) counts the cut's packets,
not a queue's, and neither decides nor smooths in: after a cut longer than this, the first
report came back before the feedback did (or with it) and read 60-90 % lost, a collapse cut to
a tenth of the bitrate on a link whose capacity never changed."""
RTX_PAUSE_S = 0.3
"""Retransmissions stop this long after the last window that saw the queue building (one
window: the queue has drained by then, at the cut bitrate), or until a window shows it
draining (then a keyframe goes out on the emptying link)."""
HOLD_AFTER_OVERUSE_S = 2.0
"""No climbing for this long after an overuse: the queue first drains, the receiver reports
catch up."""
DRAIN_PAUSE_S = 0.1
"""At the first overuse the encoder gets no frames for this long: every frame sent into an
overflowing queue loses packets and breaks the picture until a keyframe, so none is sent
until the queue has drained (the emulator's 100 ms of queue at the new capacity; the next
camera frame and the encoder's restart at the smaller size add 30-60 ms: measured 0.16 s
from the pause to the keyframe, 0.19-0.23 s with a 150 ms pause); then a keyframe at the
lowered bitrate crosses an empty link (a packet of it lost is sent again)."""
PAUSE_CUT = 0.3
"""At the pause confirmed by lossy receiver reports the bitrate falls to at most this share (a radio's capacity drop is a change
of modulation, 2-4 times: the emulator's 2 Mbit/s → 500 kbit/s is 4)."""
STALE_RETRANSMISSION_S = 1.0
"""For this long after the pause, packets sent before it are not sent again (the receivers
ask for them for their 200 ms repair budget: the picture restarts at the keyframe after the
pause, and their retransmissions would queue ahead of it on the drained link)."""
SILENCE_S = 0.1
"""Transport feedback silent this long, and :data:`SILENCE_INTERVALS` of its usual interval
(~30 ms at full rate, ~100 ms at 100 kbit/s), was a link cut, not a queue: the windows read
after it span the silence (measured after a 300 ms blackout: a delay trend of +0.98 ms read
across the gap, 92 ms of "queue growth", and the blackout's packets all lost, delivered 0.29,
confirmed by a receiver report losing 58 of 80: three cuts to 350 kbit/s on a link that never
changed). A queue over capacity keeps the feedback coming, only slower."""
SILENCE_INTERVALS = 3.0
QUEUE_BEFORE_SILENCE_MS = 15.0
"""A silence that came while the per-packet feedback saw a queue this long twice running (its
newest packet's wait, :class:`~brasidas.media.twcc.QueueDetector`) is the queue's own, not a cut: at a capacity
drop the capped return link holds the feedback back too (measured at 2 Mbit/s → 500 kbit/s:
the feedback slowed from every 25 ms to 50-90 ms, stalled 0.6 s on a loaded machine, while the
first feedbacks after the drop read waits of 21, 31, 63 ms); set aside, the drop waited for the
per-packet path (gaps 198-275 ms against ~100). A link cut drops, it does not queue: the
feedbacks before each 300 ms blackout read 0-12 ms, a loaded machine's lone spike up to 78 ms
(so two readings), the first after it up to 105 ms (a packet held in the relay across the cut:
so the readings before the silence decide)."""
AFTER_SILENCE_S = TRANSPORT_WINDOW_S + 0.05
"""The windows read this long after a silence still count its lost packets: none decides."""
PAUSE_AGAIN_AFTER_S = 1.0
"""One pause an overuse: the feedback windows (300 ms) go on showing the overflow after the
pause began, and would keep it going."""


class BitrateController:
    """The target bitrate (kbit/s) for the encoder."""

    def __init__(self, ceiling_kbps: int, floor_kbps: int) -> None:
        self.floor_kbps = floor_kbps
        self.target_kbps = float(ceiling_kbps)
        self.loss = 0.0
        """Smoothed fraction lost of the worst receiver."""
        self.decreases = 0
        self.collapsed_at: float | None = None
        """When a capacity drop was last confirmed: a report losing over
        :data:`COLLAPSE_LOSS`, then within :data:`COLLAPSE_CONFIRM_S` another losing over
        :data:`CONGESTED_LOSS` (the queue still overflowing; under a loaded emulator a single
        report spiked now and then)."""
        self._collapse_report_at: float | None = None
        self._last_step: float | None = None
        self.overused_at: float | None = None
        """When transport feedback last showed the link over its capacity."""
        self.transport_at: float | None = None
        """When transport feedback last came: while it comes, it alone lowers the bitrate."""
        self.overuses = 0
        self.queue_overuses = 0
        """Of those, seen packet by packet (:meth:`on_queue`)."""
        self._queue_cut_at: float | None = None
        self.queue_ms = 0.0
        """The link's queue as the delay's growth estimates it (ms of waiting)."""
        self.capacity_kbps = 0.0
        """What the link delivered when last over its capacity."""
        self._overuse_streak = 0
        self._streak_at = 0.0
        self._candidate: tuple[TransportReport, float] | None = None
        """The newest window that showed an overuse not yet confirmed (one read), and when."""
        self._draining = False
        self.paused_at: float | None = None
        """When the encoder's frames were last paused for a queue to drain."""
        self.pauses = 0
        self.report_loss = 0.0
        """The share lost over the newest reports that confirmed an overuse
        (:meth:`note_report`)."""
        self._report_loss_at: float | None = None
        self._reports: dict[int, list[tuple[float, int, int]]] = {}
        self.silences = 0
        """Transport feedback that stopped and came back (a link cut: :data:`SILENCE_S`)."""
        self.silence_ended_at: float | None = None
        self._feedback_interval_s: float | None = None
        """The usual time between windows read (smoothed)."""
        self.queue_stalls = 0
        """Silences that came while a queue built (:data:`QUEUE_BEFORE_SILENCE_MS`): read on."""
        self._packet_queues_ms = (0.0, 0.0)
        """The per-packet feedback's two newest queues (:meth:`note_queue`)."""
        self._queue_at_last_window_ms = 0.0
        """That queue when the last window was read: the one before a silence after it."""
        self._silence_began_at: float | None = None
        """When the feedback before the last silence came (the link cut's start, about)."""
        self._report_at: float | None = None
        """When the last receiver report with a fraction lost came (:meth:`update`)."""
        self.cut_reports = 0
        """Receiver reports set aside: their interval spanned a link cut."""

    def note_report(self, receiver: int, highest_seq: int, lost: int, now: float) -> None:
        """A receiver report's cumulative counts (its extended highest sequence number and
        packets lost), before the transport window is read: reports losing most of their
        last :data:`CONFIRM_PACKETS` packets or more confirm a growing queue at once. One
        report may cover a single packet (they come every ~20 ms; at 5 fps 26 packets a
        second: 100 % of one lost packet is a mesh's routine)."""
        reports = self._reports.setdefault(receiver, [])
        reports.append((now, highest_seq, lost))
        del reports[: max(0, len(reports) - 16)]
        for at, highest, lost_then in reversed(reports[:-1]):
            expected = highest_seq - highest
            if now - at > CONFIRM_SPAN_S or expected <= 0:
                break
            if expected >= CONFIRM_PACKETS:
                share = (lost - lost_then) / expected
                if share > COLLAPSE_LOSS:
                    self.report_loss = share
                    self._report_loss_at = now
                return

    def note_queue(self, queue_ms: float) -> None:
        """Each transport feedback's wait of its newest packet in the link's queue (read packet
        by packet): a silence after a queue is the queue's, not a cut."""
        self._packet_queues_ms = (self._packet_queues_ms[1], queue_ms)

    def _loss_confirms(self, now: float) -> bool:
        at = self._report_loss_at
        return at is not None and now - at < TRANSPORT_WINDOW_S and not self._after_silence(at)

    def _is_silence(self, gap_s: float) -> bool:
        """Whether feedback ``gap_s`` apart had a silence between them (by the usual interval)."""
        usual = self._feedback_interval_s
        return usual is not None and gap_s > max(SILENCE_S, SILENCE_INTERVALS * usual)

    def _own_pause(self, now: float) -> bool:
        """Within our own drain pause's reach: nothing was sent, nothing is reported."""
        return self.paused_at is not None and now - self.paused_at < PAUSE_AGAIN_AFTER_S

    def _silent_since(self, gap_s: float) -> bool:
        """Whether windows ``gap_s`` apart had a silence between them (and the usual interval
        learned from the others)."""
        usual = self._feedback_interval_s
        silent = self._is_silence(gap_s)
        # Silences count too (less): a feedback that slowed for good (a lowered bitrate's)
        # is the usual interval within a few windows.
        self._feedback_interval_s = gap_s if usual is None else 0.8 * usual + 0.2 * gap_s
        return silent

    def _report_spans_cut(self, now: float) -> bool:
        """Whether a receiver report at ``now`` is the first since a link cut began: the
        feedback went silent (or is silent now, the report back first) and the reports with
        it. Reports that kept coming through a feedback silence count as ever."""
        began = self._silence_began_at
        at = self.transport_at
        if (
            at is not None
            and self._is_silence(now - at)
            and self._queue_at_last_window_ms < QUEUE_BEFORE_SILENCE_MS
            and not self._own_pause(now)
        ):
            began = at
        if began is None:
            return False
        last = self._report_at
        return last is None or last < began + SILENCE_S

    def _after_silence(self, now: float) -> bool:
        at = self.silence_ended_at
        return at is not None and 0 <= now - at < AFTER_SILENCE_S

    def on_transport(self, report: TransportReport, ceiling_kbps: int, now: float) -> int | None:
        """A window of transport-wide feedback at ``now``: over capacity, the target falls to
        under what arrived (at once: no smoothing, no step); the new bitrate, else None."""
        # Windows overlap: each read adds the part of its growth that is new since the last.
        last = self.transport_at
        new_share = 1.0 if last is None else min(1.0, (now - last) / TRANSPORT_WINDOW_S)
        self.transport_at = now
        # (The per-packet readings at the window before the silence: the newest may be the
        # first feedback after it, which can count a packet held across a cut.)
        queue_before, self._queue_at_last_window_ms = (
            self._queue_at_last_window_ms,
            min(self._packet_queues_ms),
        )
        # (Not the silence of our own drain pause: nothing was sent, nothing is reported.)
        if last is not None and self._silent_since(now - last) and not self._own_pause(now):
            if queue_before >= QUEUE_BEFORE_SILENCE_MS:
                # A queue building held its own feedback back: the windows read on.
                self.queue_stalls += 1
            else:
                # The delay's trend across the silence and the packets it lost are the cut's,
                # not a queue's: the estimate starts again after it.
                self.silences += 1
                self.silence_ended_at = now
                self._silence_began_at = last
                self.queue_ms = 0.0
        if self._after_silence(now):
            self._overuse_streak = 0
            self._candidate = None
            return None
        growth = report.queue_growth_ms * new_share
        self._draining = growth < 0
        self.queue_ms = max(0.0, self.queue_ms * QUEUE_LEAK + growth)
        # A window that received nothing is a cut link or a restarting receiver: no capacity.
        # A queue already draining (the cut came through) is not cut again. A link that
        # delivers what was sent is keeping up: a delay that grew there was a forwarder's
        # pause (a loaded machine's), not a capacity.
        delivered = report.received_kbps / report.sent_kbps if report.sent_kbps > 0 else 1.0
        # A report losing most packets confirms a shorter queue (the estimate lags the real
        # queue by a window: measured 15-20 ms when it had overflowed for 0.15 s already).
        confirmed = self._loss_confirms(now)
        least_queue = OVERUSE_QUEUE_MS * (CONFIRMED_QUEUE_SHARE if confirmed else 1.0)
        if (
            report.received_kbps <= 0
            or growth <= 0
            or self.queue_ms <= least_queue
            or delivered >= OVERUSE_DELIVERED
        ):
            self._overuse_streak = 0
            self._candidate = None
            return None
        # Two reads running: a forwarder's pause shows in one, then its backlog arrives at
        # once (the delay falls); a queue over capacity goes on growing. Or one, when a
        # receiver report also counts most packets lost (a pause loses none: the relay buffers).
        self._overuse_streak += 1
        if self._overuse_streak == 1:
            self._streak_at = now
        spanned = now - self._streak_at >= OVERUSE_SPAN_S
        if not confirmed and (self._overuse_streak < OVERUSE_READS or not spanned):
            self._candidate = (report, now)
            return None
        return self._overuse(report, ceiling_kbps, now, confirmed=confirmed)

    def on_queue(
        self,
        sent_kbps: float,
        capacity_kbps: float,
        ceiling_kbps: int,
        now: float,
        *,
        sent_at: float,
    ) -> int | None:
        """The per-packet feedback saw a queue fed faster than the link drains it
        (:class:`~brasidas.media.twcc.QueueDetector`), its newest packet sent at
        ``sent_at``: over capacity now, 0.15-0.2 s before the averaged windows show it.
        Pause (the first time) and cut as deep as a receiver report counting the loss would:
        cut only to 0.75x, the frames after the pause overflowed the queue again (measured:
        longest gaps 417-714 ms against 329-423). A queue of packets sent before the last
        such cut was cut for already. The new bitrate, else None."""
        if self._queue_cut_at is not None and sent_at <= self._queue_cut_at:
            return None
        self.queue_overuses += 1
        self._queue_cut_at = now
        report = TransportReport(
            sent_kbps=sent_kbps, received_kbps=capacity_kbps, delay_trend_ms=0.0
        )
        return self._overuse(report, ceiling_kbps, now, confirmed=True)

    def confirm_pending(self, ceiling_kbps: int, now: float) -> int | None:
        """No new window, but a receiver report losing most packets just came: a window read
        moments ago that showed the queue (one read, not yet two) is confirmed by it now
        (measured: such a report 20 ms after the window, the next window 45 ms later)."""
        candidate = self._candidate
        if candidate is None or not self._loss_confirms(now):
            return None
        report, at = candidate
        if now - at > CANDIDATE_S:
            return None
        return self._overuse(report, ceiling_kbps, now, confirmed=True)

    def _overuse(
        self, report: TransportReport, ceiling_kbps: int, now: float, *, confirmed: bool
    ) -> int | None:
        """The link is over its capacity: pause (the first time), cut under what arrived."""
        self._candidate = None
        # Seen packet by packet within a silence's windows (a loaded machine's stall just
        # before a capacity drop): the windows decide again, the next cuts confirm the drop.
        self.silence_ended_at = None
        pausing = not self._own_pause(now)
        if pausing:
            self.paused_at = now
            self.pauses += 1
        self.capacity_kbps = report.received_kbps
        self.overused_at = now
        self.overuses += 1
        if report.received_kbps < report.sent_kbps * COLLAPSE_DELIVERED:
            # Most of it dropped: a capacity drop, as a receiver report losing > 35 % says.
            seen = self._collapse_report_at
            if seen is not None and 0 < now - seen <= COLLAPSE_CONFIRM_S:
                self.collapsed_at = now
            self._collapse_report_at = now
        before = self.effective_kbps(ceiling_kbps)
        current = min(self.target_kbps, float(ceiling_kbps))
        lowered = max(report.received_kbps * OVERUSE_BACKOFF, current * MOST_CUT)
        if pausing and confirmed:
            # The first window reads what arrived before the drop too (measured: 1050 kbit/s
            # "received" at a drop to 500): resumed at that, the frames after the pause
            # overflowed the queue again. The lagging windows after it cut on from there.
            # Only when the receivers' reports count the loss too: a loaded forwarder's
            # stall read twice (no loss) would cost seconds of a crushed bitrate.
            lowered = min(lowered, current * PAUSE_CUT)
        if lowered >= current:
            return None  # already under what the link carries
        self.target_kbps = max(float(self.floor_kbps), lowered)
        self.decreases += 1
        self._last_step = now
        after = self.effective_kbps(ceiling_kbps)
        return after if after != before else None

    def update(self, loss: float | None, ceiling_kbps: int, now: float) -> int | None:
        """A report's fraction lost (None: no receiver reported) at ``now``; the new
        target when it changed, else None."""
        if loss is not None:
            spans_cut = self._report_spans_cut(now)
            self._report_at = now
            if spans_cut:
                # The cut's lost packets: no congestion to cut for, no loss to repair.
                self.cut_reports += 1
                loss = None
        if loss is not None:
            self.loss = SMOOTHING * loss + (1 - SMOOTHING) * self.loss
        loss_decides = True
        if self._transport_fresh(now):
            # The delay tells a full queue from a mesh's random loss, which loss alone cannot
            # (at 10 % random loss, reports over 35 % came now and then): the transport
            # feedback alone lowers the bitrate; these reports may still raise it.
            loss_decides = False
        collapse = loss_decides and loss is not None and loss > COLLAPSE_LOSS
        last = self._collapse_report_at
        if loss_decides and loss is not None and loss > CONGESTED_LOSS and last is not None:
            if 0 < now - last <= COLLAPSE_CONFIRM_S:
                self.collapsed_at = now
        if collapse:
            self._collapse_report_at = now
        gap = DECREASE_GAP_S if collapse else STEP_S
        if self._last_step is not None and now - self._last_step < gap:
            return None
        self._last_step = now
        before = self.effective_kbps(ceiling_kbps)
        if loss_decides and loss is not None and (collapse or self.loss > CONGESTED_LOSS):
            # What got through: over capacity, the loss is the excess (a full queue drops it).
            worst = max(loss, self.loss) if collapse else self.loss
            lowered = min(self.target_kbps, float(ceiling_kbps)) * (1 - worst) * 0.95
            self.target_kbps = max(float(self.floor_kbps), lowered)
            self.decreases += 1
        elif loss is not None and self._clean(now) and not self._holding(now):
            # Up to the ceiling; a target above it (a lower framerate's) is kept for later.
            # Under what the link delivered when last over its capacity (a pause's deep cut
            # went further): back there sooner.
            climb = (
                CLIMB_TO_CAPACITY if self.target_kbps < self._remembered_capacity(now) else CLIMB
            )
            raised = max(self.target_kbps * climb, self.target_kbps + 10)
            limit = self._climb_limit(float(ceiling_kbps), now)
            self.target_kbps = max(self.target_kbps, min(raised, limit))
        after = self.effective_kbps(ceiling_kbps)
        return after if after != before else None

    def _clean(self, now: float) -> bool:
        """Room to climb: hardly any loss reported and, with transport feedback, no queue in
        the delay. Under random loss, back up to the capacity a wrong cut measured (a full
        queue's loss looks the same, and its delay stops growing once it overflows)."""
        if not self._transport_fresh(now):
            return self.loss < CLEAN_LOSS
        if self.queue_ms >= CLEAN_QUEUE_MS:
            return False
        return self.loss < CLEAN_LOSS or self.target_kbps < self._remembered_capacity(now)

    def _climb_limit(self, ceiling: float, now: float) -> float:
        """The ceiling, or for a while after the link was over its capacity, under what it
        delivered then: no probing straight back into the queue."""
        remembered = self._remembered_capacity(now)
        return min(ceiling, remembered) if remembered > 0 else ceiling

    def _remembered_capacity(self, now: float) -> float:
        """Under what the link last delivered over its capacity, for a while; else 0."""
        at = self.overused_at
        if at is None or now - at >= CAPACITY_MEMORY_S:
            return 0.0
        return CLIMB_UNDER * self.capacity_kbps

    def _transport_fresh(self, now: float) -> bool:
        at = self.transport_at
        return at is not None and now - at < TRANSPORT_FRESH_S

    def _holding(self, now: float) -> bool:
        at = self.overused_at
        return at is not None and now - at < HOLD_AFTER_OVERUSE_S

    def settling(self, now: float) -> bool:
        """The link was over its capacity moments ago (its queue may still be draining)."""
        return self._holding(now)

    def retransmissions_paused(self, now: float) -> bool:
        """While a queue overflows, retransmitting what it dropped only feeds it (measured at
        the 500 kbit/s drop: 2-3 Mbit/s sent for a second, most of it retransmissions)."""
        paused = self.paused_at
        if paused is not None and now - paused < PAUSE_AGAIN_AFTER_S:
            # The link drains while no frame is sent; after the pause only the packets sent
            # before it are not sent again (the sender's stale filter): a packet of the
            # keyframe after it, lost, is worth a retransmission.
            return now - paused < DRAIN_PAUSE_S
        at = self.overused_at
        return at is not None and now - at < RTX_PAUSE_S and not self._draining

    def effective_kbps(self, ceiling_kbps: int) -> int:
        """What the encoder is set to: the target within the framerate's ceiling."""
        return max(self.floor_kbps, round(min(self.target_kbps, float(ceiling_kbps))))


PACER_BACKLOG_S = 0.08
"""A raw frame is skipped (never encoded) while what was encoded before it would still take
longer than this to leave at the target bitrate: the encoder's own rate control follows a
lowered bitrate only over several frames (measured: 6 kB frames for 0.1-0.2 s after a cut
to a third), and every frame sent meanwhile into a full link's queue loses packets. Above a
keyframe and a frame (a 1.5 Mbit/s keyframe is ~55 ms of it), so a link that keeps up never
skips one."""


class FrameBudget:
    """The sender's view of its own queue (sans-IO): the bits encoded, leaving at the target
    bitrate. A frame is encoded only while that queue is short, so the bitrate is held at
    once, whatever the encoder's rate control does, and frames never pile up on a link."""

    def __init__(self, kbps: float) -> None:
        self.kbps = kbps
        self.backlog_bits = 0.0
        self.skipped = 0
        """Frames not encoded because the queue was long (or paused for the link's to drain)."""
        self.paused_until = 0.0
        self.enforced_until = 0.0
        """Frames are skipped only until this: for a while after the link was over its
        capacity (elsewhere a keyframe's burst at 5 fps would cost the next frame)."""
        self._at: float | None = None

    def _drain(self, now: float) -> None:
        if self._at is not None and now > self._at:
            self.backlog_bits = max(0.0, self.backlog_bits - (now - self._at) * self.kbps * 1000)
        self._at = now if self._at is None else max(self._at, now)

    def set_rate(self, kbps: float, now: float) -> None:
        self._drain(now)
        self.kbps = max(1.0, kbps)

    def backlog_s(self, now: float) -> float:
        self._drain(now)
        return self.backlog_bits / (self.kbps * 1000)

    def admit(self, now: float) -> bool:
        """A raw frame at ``now``: True to encode it, False to skip it."""
        if now < self.paused_until:
            self.skipped += 1
            return False
        if self.backlog_s(now) <= PACER_BACKLOG_S or now >= self.enforced_until:
            return True
        self.skipped += 1
        return False

    def on_encoded(self, size_bytes: int, now: float) -> None:
        self._drain(now)
        self.backlog_bits += size_bytes * 8

    def pause(self, seconds: float, now: float) -> None:
        """Encode nothing for ``seconds`` (a link's queue drains first), then hold the
        bitrate for :data:`CAPACITY_MEMORY_S`."""
        self._drain(now)
        self.enforced_until = now + CAPACITY_MEMORY_S
        self.paused_until = now + seconds
        # What was encoded before is through or lost by the pause's end: counted at the
        # lowered bitrate it would hold the frames after it back for seconds.
        self.backlog_bits = 0.0


THIN_AFTER_COLLAPSE_S = 10.0
"""Frames are thinned only this long after a capacity drop was seen: a bitrate lowered by a
mesh's random loss (which loss alone cannot tell apart) keeps every frame."""
MIN_THINNED_FPS = 10
"""Thinning never sends fewer frames than this (nor thins a stream already at or below it)."""


def frame_thinning(framerate: int, bitrate_kbps: int, ceiling_kbps: int) -> int:
    """Send one frame in N when the link forced the bitrate far below the framerate's share:
    fewer frames with twice the bits each stay legible, where every frame at a third of its
    bits smears and its larger losses freeze the picture. 1: every frame."""
    if ceiling_kbps <= 0 or framerate <= MIN_THINNED_FPS:
        return 1
    share = bitrate_kbps / ceiling_kbps
    wanted = 1 if share >= 0.5 else 2 if share >= 0.25 else 3
    return max(1, min(wanted, framerate // MIN_THINNED_FPS))


LOWER_RESOLUTION_BELOW_BPP = 0.05
"""Below this many bits per pixel the full picture smears and its frames grow large for the
bitrate: half the width and height (a quarter of the pixels) at the same bitrate stays sharp."""
FULL_RESOLUTION_ABOVE_BPP = 0.08
"""Back to the full picture above this (hysteresis: the two never alternate on one bitrate)."""
RESOLUTION_HOLD_S = 5.0
"""A size is kept at least this long: each change costs a keyframe."""


@dataclass
class ResolutionChoice:
    """Whether the NavCam sends its full picture or half its width and height (sans-IO)."""

    halved: bool = False
    changed_at: float | None = None

    def update(self, kbps: int, width: int, height: int, fps: float, now: float) -> bool:
        """The bitrate the encoder gets at ``now``: True when the size changed."""
        if self.changed_at is not None and now - self.changed_at < RESOLUTION_HOLD_S:
            return False
        bpp_full = kbps * 1000 / max(1.0, width * height * fps)
        wanted = (
            bpp_full < FULL_RESOLUTION_ABOVE_BPP
            if self.halved
            else bpp_full < LOWER_RESOLUTION_BELOW_BPP
        )
        if wanted == self.halved:
            return False
        self.halved = wanted
        self.changed_at = now
        return True

    def size(self, width: int, height: int) -> tuple[int, int]:
        """The picture sent (even sizes: H.264's 4:2:0 chroma)."""
        if not self.halved:
            return width, height
        return width // 4 * 2, height // 4 * 2
