"""The link emulator's schedule with fake time: loss, delay, jitter, reordering, duplicates, cuts."""

from __future__ import annotations

import pytest

from brasidas.netem.core import Impairment, Profile


def _run(link: Impairment, count: int, spacing: float, until: float) -> list[tuple[float, bytes]]:
    """Feed ``count`` numbered frames ``spacing`` apart; collect (time, frame) in 1 ms steps."""
    out: list[tuple[float, bytes]] = []
    now, sent = 0.0, 0
    while now <= until:
        while sent < count and sent * spacing <= now + 1e-9:
            link.feed(sent.to_bytes(4, "big"), now)
            sent += 1
        out.extend((now, frame) for frame in link.due(now))
        now = round(now + 0.001, 6)
    return out


def test_clean_link_delivers_everything_at_once_in_order() -> None:
    link = Impairment()
    delivered = _run(link, 100, 0.01, 1.5)
    assert [int.from_bytes(f, "big") for _, f in delivered] == list(range(100))
    assert all(abs(t - n * 0.01) < 0.0015 for n, (t, _) in enumerate(delivered))


def test_loss_rate_and_replay_from_the_seed() -> None:
    profile = Profile(loss=0.1, delay=0.05, jitter=0.02)
    first = _run(Impairment(profile, seed=7), 2000, 0.005, 11)
    again = _run(Impairment(profile, seed=7), 2000, 0.005, 11)
    other = _run(Impairment(profile, seed=8), 2000, 0.005, 11)
    assert first == again  # a failing run replays exactly from its seed
    assert first != other
    assert 0.08 < 1 - len(first) / 2000 < 0.12


def test_delay_and_jitter_bound_each_frame_and_reorder_some() -> None:
    link = Impairment(Profile(delay=0.05, jitter=0.02), seed=1)
    sent_at = {n: n * 0.005 for n in range(1000)}
    delivered = _run(link, 1000, 0.005, 6)
    latencies = [t - sent_at[int.from_bytes(f, "big")] for t, f in delivered]
    assert len(delivered) == 1000
    assert min(latencies) >= 0.03 - 0.0015
    assert max(latencies) <= 0.07 + 0.0015
    order = [int.from_bytes(f, "big") for _, f in delivered]
    assert order != sorted(order)  # 5 ms apart, ±20 ms: frames overtake each other


def test_reorder_sends_some_ahead_and_duplicates_copy() -> None:
    link = Impairment(Profile(delay=0.1, reorder=0.2, duplicate=0.1), seed=3)
    delivered = _run(link, 1000, 0.01, 11)
    order = [int.from_bytes(f, "big") for _, f in delivered]
    assert 0.15 < link.counters.reordered / 1000 < 0.25
    assert 0.07 < link.counters.duplicated / 1000 < 0.13
    assert len(order) == 1000 + link.counters.duplicated
    assert order != sorted(order)


def test_cut_drops_arrivals_and_frames_in_flight_until_restored() -> None:
    link = Impairment(Profile(delay=0.1))
    link.feed(b"in flight", 0.0)
    link.cut()
    link.feed(b"during", 0.05)
    assert link.due(1.0) == []
    assert link.deadline() is None
    link.restore()
    link.feed(b"after", 1.0)
    assert link.deadline() == pytest.approx(1.1)
    assert link.due(1.1) == [b"after"]
    assert link.counters.cut == 2


def test_profile_refuses_nonsense() -> None:
    with pytest.raises(ValueError, match="loss"):
        Profile(loss=1.5)
    with pytest.raises(ValueError, match="delay"):
        Profile(delay=-1)


def test_a_rate_limit_spaces_frames_and_drops_beyond_its_queue() -> None:
    # 1000-byte frames offered at 2 Mbit/s into an 800 kbit/s link (100 B per ms).
    link = Impairment(Profile(rate_kbps=800, burst_bytes=1000, queue_s=0.05))
    out: list[tuple[float, bytes]] = []
    now = 0.0
    for n in range(1000):  # 4 s, one frame every 4 ms
        now = n * 0.004
        link.feed(bytes(1000), now)
        out.extend((now, f) for f in link.due(now))
    now += 1
    out.extend((now, f) for f in link.due(now))
    delivered_bytes = 1000 * len(out)
    assert 0.95 < delivered_bytes * 8 / 4 / 800_000 < 1.1  # the capacity, not the offer
    assert link.counters.overflow == 1000 - len(out)
    assert link.in_flight == 0
    # Below the rate, nothing waits and nothing is dropped.
    calm = Impairment(Profile(rate_kbps=800, burst_bytes=1000))
    assert _run(calm, 100, 0.02, 3)
    assert calm.counters.overflow == 0
    with pytest.raises(ValueError, match="rate_kbps"):
        Profile(rate_kbps=-1)
