"""The one capped exponential backoff: growth, cap, reset, jitter bounds."""

from __future__ import annotations

import itertools

import pytest

from brasidas.backoff import Backoff


def test_grows_by_factor_to_the_cap_without_jitter() -> None:
    backoff = Backoff(0.2, 2.0, jitter=0.0)
    assert [round(backoff.next(), 6) for _ in range(7)] == [0.2, 0.4, 0.8, 1.6, 2.0, 2.0, 2.0]
    assert backoff.attempts == 7


def test_reset_starts_over() -> None:
    backoff = Backoff(0.5, 8.0, factor=3.0, jitter=0.0)
    assert [backoff.next() for _ in range(3)] == [0.5, 1.5, 4.5]
    backoff.reset()
    assert backoff.attempts == 0
    assert backoff.next() == 0.5


def test_jitter_only_shortens_within_its_fraction() -> None:
    source = itertools.cycle([0.0, 0.5, 0.999])
    backoff = Backoff(1.0, 1.0, jitter=0.2, random=lambda: next(source))
    assert [round(backoff.next(), 4) for _ in range(3)] == [1.0, 0.9, 0.8002]


def test_jitter_spreads_retries_started_together() -> None:
    delays = {round(Backoff(1.0, 10.0).next(), 9) for _ in range(50)}
    assert len(delays) > 10  # the default source really jitters
    assert all(0.9 <= delay <= 1.0 for delay in delays)


@pytest.mark.parametrize(
    ("initial", "maximum", "factor", "jitter"),
    [(0.0, 1.0, 2.0, 0.1), (2.0, 1.0, 2.0, 0.1), (1.0, 2.0, 0.5, 0.1), (1.0, 2.0, 2.0, 1.0)],
)
def test_nonsense_refused(initial: float, maximum: float, factor: float, jitter: float) -> None:
    with pytest.raises(ValueError, match="backoff"):
        Backoff(initial, maximum, factor=factor, jitter=jitter)
