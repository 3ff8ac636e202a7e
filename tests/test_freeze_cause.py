"""The overlay names the cause of a freeze from the receiver's loss and repair counters."""

from __future__ import annotations

from brasidas.media.repair import RepairCounters
from stationd.video_feed import AccessUnit, Feed


class _Repairs:
    def __init__(self) -> None:
        self.now = RepairCounters()

    def counters(self) -> RepairCounters:
        return self.now


def test_a_loss_beyond_repair_is_named_and_a_quiet_link_is_not() -> None:
    feed = Feed("rover", 1, host="127.0.0.1", port=1)
    repairs = _Repairs()
    feed.depayloader.repairs = repairs  # type: ignore[assignment]
    feed.fanout.feed(AccessUnit(b"k", True, 1.0, 2.0))
    assert feed.loss_reason() == ""

    # Repaired losses freeze nothing and are not a cause.
    repairs.now = RepairCounters(repaired=12)
    assert feed.loss_reason() == ""

    # A packet given up on: the depayloader drops its frame, the picture waits for a keyframe.
    repairs.now = RepairCounters(lost=3, repaired=14)
    reason = feed.loss_reason()
    assert reason.startswith("packet loss on the link")
    assert "3 packets lost, 2 repaired" in reason
    assert feed.loss_reason() == ""  # nothing new since

    # A gap the fan-out saw (deltas held back until the next keyframe) is loss too.
    feed.fanout.feed(AccessUnit(b"d", False, 3.0, 4.0, after_gap=True))
    assert feed.loss_reason().startswith("packet loss on the link")
