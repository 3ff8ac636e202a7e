"""A station's connection to one platform: authenticated connect, heartbeats, signaling calls."""

from __future__ import annotations

import asyncio
import collections
import contextlib
import logging
import math
import secrets
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any
from urllib.parse import urlsplit

from brasidas import security
from brasidas.codecs.beacon import boot_proof
from brasidas.codecs.jsonrpc import UNAUTHORIZED, EncodedParams, RpcError
from brasidas.rpc import RpcClient
from brasidas.security import accept_proof, connect_proof

_LOGGER = logging.getLogger(__name__)


CLOSED_BY_STATION = "closed by station"
"""The close reason of a session this station ended itself (not a loss)."""


class AuthenticationError(Exception):
    """The platform refused us, or could not prove it holds the fleet key."""


@dataclass(frozen=True)
class ClockSample:
    """One heartbeat's clock exchange: the platform's clock minus ours (s), and the round trip
    it was measured over (s); the offset is within half the round trip of the truth."""

    offset: float
    round_trip: float
    at: float = 0.0
    """When it was measured (our clock)."""

    def error_bound(self, now: float) -> float:
        """How far off the offset may be at ``now`` (s): half its round trip, plus what the
        two clocks may have drifted apart since (:data:`CLOCK_DRIFT`)."""
        return self.round_trip / 2 + CLOCK_DRIFT * max(0.0, now - self.at)


CLOCK_DRIFT = 500e-6
"""How fast two hosts' monotonic clocks may drift apart (s/s): NTP's slew limit, well above a
crystal's tens of ppm. A quick round trip a minute old is still within 30 ms."""
CLOCK_SAMPLES = 256
"""Heartbeats kept for the offset (four minutes at the default second)."""
FREEZE_CHECK_S = 0.1
"""How often the picture's age is looked at between heartbeats (it costs no traffic)."""
FREEZE_REPORT_MS = 100.0
"""Report the picture's age before the next heartbeat once it grew this much since the last
report (a freeze; the picture's return waits for the heartbeat: raising the cap can)."""


class ClockOffset:
    """The platform's monotonic clock relative to ours, from the heartbeats (NTP-style, sans-IO).

    Each heartbeat gives ``sent`` and ``received`` (our clock) and the platform's clock when it
    answered; assuming the answer was made halfway, the offset is ``platform - (sent +
    received) / 2``, off by at most half the round trip. Like NTP's clock filter, the sample
    of the smallest error bound is used (half its round trip, grown by the clocks' possible
    drift since): a heartbeat delayed one way skews its sample, a quick one cannot. Kept for
    minutes, so that a queue on one direction only (the platform's video filling its radio
    link) does not push out every quick sample: each of its heartbeats is skewed by half the
    queue, and the packets the platform aged by it looked that much older than they were
    (~97 ms with a 200 ms queue platform → station, measured).
    """

    def __init__(self, keep: int = CLOCK_SAMPLES) -> None:
        self.samples: collections.deque[ClockSample] = collections.deque(maxlen=keep)

    def add(self, sent: float, platform: float, received: float) -> ClockSample:
        sample = ClockSample(platform - (sent + received) / 2, received - sent, received)
        self.samples.append(sample)
        return sample

    @property
    def best(self) -> ClockSample | None:
        """The sample of the smallest error bound now (at the newest), None before the first
        heartbeat."""
        if not self.samples:
            return None
        now = self.samples[-1].at
        return min(self.samples, key=lambda sample: sample.error_bound(now))


class PlatformConnection:
    """One session with one platform. Single use: ``open()`` once, ``close()`` any number of times."""

    def __init__(
        self,
        platform_id: str,
        signaling_url: str,
        *,
        station_id: str,
        fleet_key: bytes | None,
        timeout: float = 3.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.platform_id = platform_id
        self.signaling_url = signaling_url.rstrip("/")
        self.platform_host = urlsplit(self.signaling_url).hostname or ""
        self.station_id = station_id
        self.fleet_key = fleet_key
        self.timeout = timeout
        self.session_id = ""
        self._session_params = EncodedParams.of({"session": ""})
        """The params of a call that takes no others, encoded once per session."""
        self.session_key: bytes | None = None
        self.parameters: dict[str, Any] = {}
        self.capabilities: dict[str, Any] = {}
        self.boot: int | None = None
        """The platform's boot number as it announced it, signed for this connection (None
        unsigned): discovery then takes that boot's beacons (brasidas.codecs.beacon)."""
        self.manual_override = False
        self.control = False
        """This station holds control of the platform (its last heartbeat answer said so)."""
        self.controller: str | None = None
        """The station holding control, by the last heartbeat answer."""
        self.on_control_lost: Callable[[str | None], None] | None = None
        """Called with the new holder's station id when control was taken from this station."""
        self.round_trip_ms: float | None = None
        self.clock_offset = ClockOffset()
        """The platform's clock relative to ``clock`` (this station's monotonic clock)."""
        self._clock = clock
        self.video_latency: Callable[[], float | None] | None = None
        """The NavCam's measured glass-to-glass latency (ms) now, set by stationd.media: while
        this station holds the override, each heartbeat reports it (the platform's speed cap)."""
        self._reported_video_ms = math.inf
        """The video latency last reported (inf: none yet, nothing to report early)."""
        self.closed = asyncio.Event()
        self.close_reason = ""
        self._client = RpcClient(self.signaling_url + "/rpc/ws", timeout=timeout)
        self._connect_answer: dict[str, Any] = {}
        self._heartbeat: asyncio.Task[None] | None = None
        self._watcher: asyncio.Task[None] | None = None

    async def open(self) -> None:
        """Connect and authenticate (both ways); raises on failure, leaving nothing open."""
        try:
            await asyncio.wait_for(self._client.open(), self.timeout)
            await self._handshake()
        except BaseException:
            await self._client.close()
            raise
        loop = asyncio.get_running_loop()
        interval = float(self._connect_answer.get("heartbeat_interval", 1.0))
        self._heartbeat = loop.create_task(
            self._heartbeats(interval), name=f"heartbeat:{self.platform_id}"
        )
        self._watcher = loop.create_task(self._watch(), name=f"watch:{self.platform_id}")

    async def _handshake(self) -> None:
        challenge = await self._client.call("challenge")
        if challenge.get("platform_id") != self.platform_id:
            raise AuthenticationError(
                f"{self.signaling_url} is platform {challenge.get('platform_id')!r}, not {self.platform_id!r}"
            )
        nonce = str(challenge.get("nonce", ""))
        station_nonce = secrets.token_hex(16)
        params: dict[str, Any] = {"station_id": self.station_id}
        if self.fleet_key is not None:
            proof = connect_proof(
                self.fleet_key, self.platform_id, self.station_id, nonce, station_nonce
            )
            params.update(nonce=nonce, station_nonce=station_nonce, proof=proof)
        elif challenge.get("auth") != "none":
            raise AuthenticationError("platform requires a fleet key and this station has none")
        try:
            answer = await self._client.call("connect", params)
        except RpcError as err:
            raise AuthenticationError(f"connect refused: {err.message}") from None
        token = str(answer["session"])
        if self.fleet_key is not None:
            expected = accept_proof(
                self.fleet_key, self.platform_id, self.station_id, nonce, station_nonce, token
            )
            if not security.verify(expected.encode(), str(answer.get("proof", "")).encode()):
                raise AuthenticationError("platform failed to prove it holds the fleet key")
            self.session_key = security.session_key(self.fleet_key, token, nonce, station_nonce)
            self.boot = _announced_boot(answer, self.fleet_key, self.platform_id, station_nonce)
        self.session_id = token
        self._session_params = EncodedParams.of({"session": token})
        self.parameters = dict(answer.get("parameters", {}))
        self.capabilities = dict(answer.get("capabilities", {}))
        self._connect_answer = answer

    async def call(self, method: str, **params: Any) -> Any:
        """A session method call; raises RpcError on an error answer or no answer in time."""
        if self.closed.is_set():
            raise ConnectionError(f"connection to {self.platform_id} closed ({self.close_reason})")
        if not params:
            return await self._client.call(method, self._session_params)
        params["session"] = self.session_id
        return await self._client.call(method, params)

    def platform_time_ms(self) -> int | None:
        """Now in the platform's monotonic clock (ms) by the offset estimate, None before the
        first heartbeat answered: what ``$PVEL`` carries as its send time."""
        best = self.clock_offset.best
        return None if best is None else round((self._clock() + best.offset) * 1000)

    async def _heartbeats(self, interval: float) -> None:
        misses = 0
        delay = 0.0  # the first at once: the clock offset is known before the first packet
        while True:
            await self._wait_reporting_freezes(delay)
            delay = interval
            try:
                await self.heartbeat()
            except RpcError as err:
                misses += 1
                _LOGGER.warning("heartbeat to %s failed: %s", self.platform_id, err.message)
                if err.code == UNAUTHORIZED or misses >= 3:
                    self._mark_closed(f"heartbeat failed: {err.message}")
                    await self._client.close()
                    return
                continue
            except ConnectionError:
                return
            misses = 0
            await self._report_latency()

    async def heartbeat(self) -> None:
        """One heartbeat: keeps the session, measures the round trip and the clock offset, and
        learns the override and control state (``on_control_lost`` when control was taken).
        Raises RpcError or ConnectionError as :meth:`call`."""
        started = time.perf_counter()
        sent = self._clock()
        answer = await self.call("heartbeat")
        self.round_trip_ms = (time.perf_counter() - started) * 1000
        platform_clock = answer.get("clock")
        if (
            isinstance(platform_clock, int | float)
            and not isinstance(platform_clock, bool)
            and math.isfinite(platform_clock)
        ):
            self.clock_offset.add(sent, float(platform_clock), self._clock())
        self.manual_override = bool(answer.get("manual_override"))
        self._update_control(answer)

    async def _wait_reporting_freezes(self, delay: float) -> None:
        """Wait ``delay`` (till the next heartbeat), reporting the picture's age at once when
        it grew FREEZE_REPORT_MS past the last report: a picture freezing between heartbeats
        (1 s apart) would leave the cap up to a second too high; this way it falls within
        about FREEZE_CHECK_S of the age that calls for it."""
        loop = asyncio.get_running_loop()
        until = loop.time() + delay
        while (left := until - loop.time()) > 0:
            await asyncio.sleep(min(left, FREEZE_CHECK_S))
            if not self.manual_override or self.video_latency is None:
                continue
            video = self.video_latency()
            if video is not None and video >= self._reported_video_ms + FREEZE_REPORT_MS:
                await self._report_latency()

    async def _report_latency(self) -> None:
        video = self.video_latency() if self.video_latency is not None else None
        if not self.manual_override or video is None or self.round_trip_ms is None:
            return
        self._reported_video_ms = video
        with contextlib.suppress(RpcError):  # a platform without a speed cap
            await self.call("report_latency", video_ms=video, command_ms=self.round_trip_ms / 2)

    def _update_control(self, answer: dict[str, Any]) -> None:
        had = self.control
        self.control = bool(answer.get("control"))
        holder = answer.get("controller")
        self.controller = str(holder) if holder is not None else None
        if had and not self.control and self.on_control_lost is not None:
            self.on_control_lost(self.controller)

    async def _watch(self) -> None:
        await self._client.closed.wait()
        self._mark_closed(self.close_reason or "connection lost")

    def _mark_closed(self, reason: str) -> None:
        if not self.closed.is_set():
            self.close_reason = reason
            self.closed.set()

    async def close(self) -> None:
        """Say goodbye (briefly) and release everything. Idempotent."""
        if not self.closed.is_set() and self.session_id:
            with contextlib.suppress(Exception):
                await self._client.call("disconnect", {"session": self.session_id}, timeout=0.5)
        self._mark_closed(self.close_reason or CLOSED_BY_STATION)
        current = asyncio.current_task()
        for task in (self._heartbeat, self._watcher):
            if task is not None and task is not current:
                task.cancel("connection closing")
                with contextlib.suppress(asyncio.CancelledError, Exception):
                    await task
        self._heartbeat = self._watcher = None
        await self._client.close()

    def _clock_summary(self) -> dict[str, float] | None:
        best = self.clock_offset.best
        if best is None:
            return None
        return {
            "offset_s": best.offset,
            "error_ms": round(best.error_bound(self._clock()) * 1000, 3),
        }

    def summary(self) -> dict[str, Any]:
        return {
            "platform_id": self.platform_id,
            "signaling_url": self.signaling_url,
            "session": self.session_id,
            "connected": not self.closed.is_set(),
            "close_reason": self.close_reason,
            "manual_override": self.manual_override,
            "control": self.control,
            "controller": self.controller,
            "round_trip_ms": self.round_trip_ms,
            "clock_offset": self._clock_summary(),
            "parameters": self.parameters,
            "capabilities": self.capabilities,
        }


def _announced_boot(
    answer: dict[str, Any], key: bytes, platform_id: str, station_nonce: str
) -> int | None:
    boot = answer.get("boot")
    if not isinstance(boot, int) or isinstance(boot, bool) or not 0 < boot < 2**32:
        return None
    expected = boot_proof(key, platform_id, boot, station_nonce)
    received = str(answer.get("boot_proof", ""))
    return boot if security.verify(expected.encode(), received.encode()) else None
