"""Admission before work (issue 19): the policy with a stepped clock, and the accept loop
out of file descriptors. The attacks themselves: tests/test_hostile_signaling.py."""

from __future__ import annotations

import asyncio
import errno
import logging
import socket
from collections.abc import Awaitable, Callable
from typing import Any

import pytest
from conftest import wait_until

from brasidas.admission import (
    AdmissionLimits,
    AdmissionPolicy,
    AdmittingListener,
    RefusalTally,
)
from brasidas.config import ConfigError, PlatformConfig, StationConfig, load_config
from platformd.app import PlatformDaemon

Factory = Callable[..., Awaitable[PlatformDaemon]]

FLOOD = b"[" + b",".join([b"{}"] * 21_000) + b"]"
"""The issue's batch: 21,000 empty objects in 64 KiB."""


# --------------------------------------------------------------------------- the policy


def test_refusals_are_tallied_per_address_over_whole_windows() -> None:
    policy = AdmissionPolicy(
        AdmissionLimits(max_strangers=4, max_strangers_per_host=1), descriptors=1024
    )
    policy.admit("10.0.0.9", 0.0)
    for step in range(30):
        policy.admit("10.0.0.9", 0.1 + step * 0.1)
    policy.admit("10.0.0.7", 3.5)
    policy.admit("10.0.0.7", 3.6)
    assert policy.refusals.top(4.0) == ("10.0.0.9", 30)
    assert policy.refusals.top(15.0) == ("10.0.0.9", 30)  # the last whole window
    assert policy.refusals.top(25.0) == ("", 0)  # two windows later: forgotten
    tally = RefusalTally(window=10.0)
    for host in range(1000):  # many addresses: the table stays bounded
        tally.count(f"10.1.{host // 250}.{host % 250}", 1.0)
    assert len(tally.current) == 256


def test_strangers_are_capped_per_host_and_the_busiest_host_gives_way() -> None:
    policy = AdmissionPolicy(
        AdmissionLimits(max_strangers=4, max_strangers_per_host=2), descriptors=1024
    )
    first, _ = policy.admit("10.0.0.9", 0.0)
    second, _ = policy.admit("10.0.0.9", 0.1)
    assert first is not None
    assert second is not None
    # The host's cap: a newcomer is refused while the host's oldest is younger than a second,
    assert policy.admit("10.0.0.9", 0.2) == (None, None)
    assert policy.counters["refused_host"] == 1
    # then the oldest gives way (a station may be behind the same address: NAT).
    third, evicted = policy.admit("10.0.0.9", 1.0)
    assert third is not None
    assert evicted is first
    assert first.closed
    assert policy.counters["evicted_host"] == 1
    assert policy.strangers["10.0.0.9"] == [second, third]
    policy.admit("10.0.0.8", 1.1)
    policy.admit("10.0.0.7", 1.2)
    station, evicted = policy.admit("10.0.0.1", 1.3)  # the total cap: the busiest host yields
    assert station is not None
    assert evicted is second
    assert second.closed
    assert policy.stranger_count == 4
    policy.session_opened(station)  # a station's now: no longer counted, never evicted
    assert policy.stranger_count == 3
    assert station in policy.slots
    for step in range(10):
        policy.admit("10.0.0.1", 2.0 + step)
        policy.admit("10.0.0.5", 2.5 + step)
    assert not station.closed
    assert station in policy.slots


def test_capacity_keeps_descriptors_in_reserve() -> None:
    limits = AdmissionLimits(max_connections=512, reserved_fds=128, trusted=True)
    assert AdmissionPolicy(limits, descriptors=4096).capacity_shortfall() is None
    assert AdmissionPolicy(limits, descriptors=1024).capacity_shortfall() is None
    policy = AdmissionPolicy(limits, descriptors=200)
    assert policy.capacity == 72
    assert "holds 72 connections, fewer than max_connections (512)" in str(
        policy.capacity_shortfall()
    )
    for number in range(72):
        assert policy.admit("127.0.0.1", number)[0] is not None
    assert policy.admit("127.0.0.1", 100.0) == (None, None)
    assert policy.counters["refused_full"] == 1


def test_header_idle_and_write_timeouts_by_the_clock() -> None:
    limits = AdmissionLimits(header_timeout=5, idle_timeout=15, write_timeout=10)
    policy = AdmissionPolicy(limits, descriptors=1024)
    silent, _ = policy.admit("10.0.0.9", 0.0)
    partial, _ = policy.admit("10.0.0.8", 0.0)
    quiet_ws, _ = policy.admit("10.0.0.7", 0.0)
    reader, _ = policy.admit("10.0.0.6", 0.0)
    assert silent
    assert partial
    assert quiet_ws
    assert reader
    policy.received(partial, 1.0)  # half a request line, then nothing
    policy.received(quiet_ws, 0.5)
    policy.request_started(quiet_ws)  # a WebSocket without a session
    policy.session_opened(reader)
    policy.request_started(reader)  # a station's WebSocket whose station stopped reading
    backlog = {reader: 4096}

    def due(now: float) -> set[Any]:
        closing = {slot for slot, _ in policy.due(now, lambda slot: backlog.get(slot, 0))}
        for slot in closing:
            policy.release(slot)
        return closing

    assert due(5.9) == set()
    assert due(6.1) == {partial}  # 5 s after its first byte
    assert due(14.9) == set()
    assert due(15.6) == {silent, quiet_ws}
    assert due(16.0) == {reader}  # 10 s since its backlog was first seen, never shrinking
    assert policy.counters["header_timeouts"] == 1
    assert policy.counters["idle_timeouts"] == 2
    assert policy.counters["slow_readers"] == 1


def test_too_much_unsent_data_closes_at_once() -> None:
    policy = AdmissionPolicy(AdmissionLimits(max_unsent_bytes=65536), descriptors=1024)
    slot, _ = policy.admit("10.0.0.9", 0.0)
    assert slot is not None
    policy.session_opened(slot)
    policy.request_started(slot)
    assert policy.due(0.1, lambda _: 70_000) == [(slot, "slow_readers")]


class _Exhausted(socket.socket):
    """A listening socket whose accept fails as when the process has no descriptor left."""

    attempts = 0

    def accept(self) -> tuple[socket.socket, Any]:
        type(self).attempts += 1
        raise OSError(errno.EMFILE, "Too many open files")


async def test_out_of_descriptors_backs_off_and_logs_once(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """asyncio's own accept loop logs per attempt and reschedules one retry per failure
    (1.55 M lines in 45 s in the issue); this one waits, longer each time, and logs once."""
    sock = _Exhausted(socket.AF_INET, socket.SOCK_STREAM)
    sock.bind(("127.0.0.1", 0))
    sock.listen()
    policy = AdmissionPolicy(AdmissionLimits(), descriptors=1024)
    listener = AdmittingListener(sock, asyncio.Protocol, policy, "test")
    listener.start()
    peers = [socket.create_connection(sock.getsockname()) for _ in range(3)]
    try:
        with caplog.at_level(logging.WARNING, "brasidas.admission"):
            await wait_until(lambda: _Exhausted.attempts >= 4, timeout=10)
        assert policy.counters["out_of_descriptors"] == _Exhausted.attempts
        # 50, 100, 200 ms, ...: a handful of attempts in the time, never a spin.
        assert _Exhausted.attempts <= 8
        assert len([r for r in caplog.records if "cannot accept" in r.message]) == 1
    finally:
        listener.close()
        for peer in peers:
            peer.close()


def test_a_strangers_address_has_a_byte_budget() -> None:
    policy = AdmissionPolicy(AdmissionLimits(stranger_bytes_per_s=1000), descriptors=1024)
    first, _ = policy.admit("10.0.0.9", 0.0)
    second, _ = policy.admit("10.0.0.9", 0.0)
    other, _ = policy.admit("10.0.0.8", 0.0)
    assert first
    assert second
    assert other
    assert policy.charge(first, 1500, 0.0) == 0.0  # a burst of twice the rate
    assert policy.charge(second, 1000, 0.0) == pytest.approx(0.5)  # the address's, shared
    assert policy.charge(other, 1000, 0.0) == 0.0
    assert policy.charge(first, 500, 2.0) == 0.0  # refilled meanwhile
    policy.session_opened(first)
    assert policy.charge(first, 10**6, 2.0) == 0.0  # a station's connection: no budget
    assert policy.counters["throttled"] == 1


def test_the_caps_are_validated_at_the_door() -> None:
    with pytest.raises(ConfigError, match=r"admission\.max_strangers: must be >= "):
        load_config(PlatformConfig, None, ["admission.max_strangers_per_host=100"])
    with pytest.raises(ConfigError, match=r"admission\.max_connections: must be >= "):
        load_config(PlatformConfig, None, ["admission.max_strangers=1000"])
    with pytest.raises(ConfigError, match=r"admission\.header_timeout"):
        load_config(PlatformConfig, None, ["admission.header_timeout=0"])
    with pytest.raises(ConfigError, match=r"admission\.max_batch"):
        load_config(StationConfig, None, ["admission.max_batch=0"])
