"""IMU: an MPU-6050 on I2C (smbus2), fused with a Madgwick filter into the platform's attitude.

The register-level driver (:mod:`brasidas.drivers.mpu6050`) wakes the chip, checks WHO_AM_I,
sets the sample rate, low-pass filter and ranges (``imu.accel_range_g``, ``imu.gyro_range_dps``). With ``imu.fifo`` (the default) the chip
queues accel + gyro samples (12 bytes each) in its 1024-byte FIFO at ``imu.rate_hz`` and the
driver drains it about 10 times a second: FIFO_COUNT, then whole samples from FIFO_R_W in
24-byte reads (an SMBus block carries at most 32), their times rebuilt evenly spaced from the
sample rate; the temperature is a separate 2-byte read once a second. An overflow (INT_STATUS
FIFO_OFLOW, a count that is not whole samples, or a full FIFO) resets the FIFO and is counted.
With ``imu.fifo=false`` it reads the 14-byte burst from 0x3B at ``imu.rate_hz`` instead (one
wake-up per sample). It publishes ``ATTITUDE`` (quaternion, roll, pitch, yaw) about 10 times a
second and ``IMU_STATUS`` (ok or the error, chip temperature, counters) about once a second.
A missing bus or chip, a wrong WHO_AM_I or repeated read errors are reported in IMU_STATUS
and retried with capped backoff.

Threading: smbus2 calls are blocking ioctls (a 14-byte burst is ~0.5 ms at 400 kHz, far more
when the bus stretches or times out), so they never run on the event loop. One sampling
thread, owned by the actor (started in ``run``, told to stop in its ``finally``), reads
on a steady clock and hands samples over in batches of ~100 ms through
``loop.call_soon_threadsafe``: ten loop wake-ups a second instead of a hundred. The fusion runs
on the loop, sample by sample (pure Python, ~20 µs a sample).
"""

from __future__ import annotations

import asyncio
import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from brasidas import topics
from brasidas.actor import Actor
from brasidas.backoff import Backoff
from brasidas.bus import Bus
from brasidas.config import ImuSection
from brasidas.drivers.mpu6050 import (
    FIFO_SAMPLE,
    FIFO_SIZE,
    BusFactory,
    ImuError,
    Mpu6050Driver,
    Sample,
    SampleClock,
    SMBusLike,
    fifo_overflowed,
)
from brasidas.madgwick import Madgwick, euler_deg
from brasidas.messages import Attitude, ImuStatus
from brasidas.threads import in_daemon_thread
from platformd.context import PlatformContext

_LOGGER = logging.getLogger(__name__)

BACKOFF_INITIAL = 0.2
BACKOFF_MAX = 5.0
STATUS_INTERVAL = 1.0
ATTITUDE_INTERVAL = 0.1
BATCH_SECONDS = 0.1
TEMPERATURE_INTERVAL = 1.0
"""FIFO mode: seconds between reads of the chip temperature."""
HEALTHY_AFTER = 10.0
"""A sampler that ran this long before failing restarts the backoff from its start."""
MAX_CONSECUTIVE_ERRORS = 10
"""Read errors in a row before the device is declared gone and reopened."""


@dataclass
class FifoBatch:
    """What the sampling thread hands over in FIFO mode (raw: converted on the loop)."""

    start: float
    """Time of the first sample; the others follow at the sample period."""
    data: bytes
    temperature_c: float | None
    errors: int
    overflows: int


class GyroBias:
    """The gyro's zero-rate offset, from the first still stretch of samples.

    An MPU-6050 reads up to ±20 °/s with no rotation (a few °/s is typical), which would turn
    straight into yaw drift. The first ``needed`` samples whose spread stays within
    ``max_spread`` (rad/s) on every axis, and whose mean is under ``max_offset``, are
    averaged; a robot moving at start delays the measure, and after ``max_attempts`` windows
    it gives up (offset 0). A turn slower than ``max_offset`` at start is taken for an offset.
    """

    def __init__(
        self,
        needed: int,
        max_spread: float = math.radians(2.0),
        max_offset: float = math.radians(10.0),
        max_attempts: int = 30,
    ) -> None:
        self.needed = needed
        self.max_spread = max_spread
        self.max_offset = max_offset
        """A steady turn looks like an offset: means larger than this are refused as one."""
        self.max_attempts = max_attempts
        self.offset = (0.0, 0.0, 0.0)
        self.done = needed <= 0
        self.measured = False
        self.attempts = 0
        self._window: list[tuple[float, float, float]] = []

    def add(self, gyro: tuple[float, float, float]) -> bool:
        """One sample; True when the measure has just ended (measured or given up)."""
        if self.done:
            return False
        self._window.append(gyro)
        if len(self._window) < self.needed:
            return False
        axes = list(zip(*self._window, strict=True))
        self._window.clear()
        x, y, z = (sum(axis) / len(axis) for axis in axes)
        still = all(max(axis) - min(axis) <= self.max_spread for axis in axes)
        if still and max(abs(x), abs(y), abs(z)) <= self.max_offset:
            self.offset = (x, y, z)
            self.done = self.measured = True
            return True
        self.attempts += 1
        if self.attempts >= self.max_attempts:
            self.done = True
            return True
        return False

    def correct(self, gyro: tuple[float, float, float]) -> tuple[float, float, float]:
        bx, by, bz = self.offset
        return (gyro[0] - bx, gyro[1] - by, gyro[2] - bz)


def smbus_factory(bus_number: int) -> SMBusLike:
    import smbus2  # imported here: only a real platform needs /dev/i2c-N

    bus: SMBusLike = smbus2.SMBus(bus_number)
    return bus


class ImuReader(Actor):
    """Samples the MPU-6050 in its own thread; fuses and publishes on the loop."""

    name = "imu"

    def __init__(self, bus: Bus, config: ImuSection, bus_factory: BusFactory | None = None):
        super().__init__(bus)
        self.config = config
        self.bus_factory = bus_factory or smbus_factory
        self.filter = Madgwick(config.madgwick_beta)
        self.gyro_bias = GyroBias(0)
        self.samples = 0
        self.read_errors = 0
        self.fifo_overflows = 0
        self.error = ""
        self.temperature_c: float | None = None
        self.attitude: Attitude | None = None
        self._last_time: float | None = None
        self._last_attitude_at = 0.0
        self._status: ImuStatus | None = None
        self._failed: asyncio.Future[str] | None = None

    async def run(self) -> None:
        async with asyncio.TaskGroup() as group:
            group.create_task(self._status_loop(), name="imu:status")
            await self._device_loop()

    async def _device_loop(self) -> None:
        loop = asyncio.get_running_loop()
        backoff = Backoff(BACKOFF_INITIAL, BACKOFF_MAX)
        failures = 0
        while True:
            # A thread of its own: an open hung in the kernel must not hold an executor worker
            # (which would keep the process from exiting).
            opening: asyncio.Future[Mpu6050Driver] = in_daemon_thread("imu-open", self._open)
            try:
                driver = await asyncio.shield(opening)
            except asyncio.CancelledError:
                # Cancelled mid-open: the thread still finishes; close what it opens.
                opening.add_done_callback(_close_opened)
                raise
            except (OSError, ImuError) as err:
                failures += 1
                self._set_error(str(err), log=failures == 1)
                await asyncio.sleep(backoff.next())
                continue
            except Exception as err:  # a driver bug or a bus misbehaving: reported, retried
                failures += 1
                _LOGGER.debug("IMU open failed", exc_info=True)
                self._set_error(f"open failed: {type(err).__name__}: {err}", log=failures == 1)
                await asyncio.sleep(backoff.next())
                continue
            _LOGGER.info(
                "IMU: MPU-6050 at 0x%02x on i2c-%d, %g Hz",
                self.config.address,
                self.config.i2c_bus,
                self.config.rate_hz,
            )
            self.error = ""
            self.filter.reset()
            self._last_time = None
            self.gyro_bias = GyroBias(round(self.config.calibrate_s * self.config.rate_hz))
            self._publish_status()
            started = loop.time()
            reason = await self._sample(driver, loop)
            failures = 1
            if loop.time() - started > HEALTHY_AFTER:
                backoff.reset()  # else a sampler failing at once is restarted ever more slowly
            self._set_error(reason, log=True)
            await asyncio.sleep(backoff.next())

    def _open(self) -> Mpu6050Driver:
        """Open the bus and set the chip up (blocking: runs in an executor thread)."""
        try:
            bus = self.bus_factory(self.config.i2c_bus)
        except OSError as err:
            raise OSError(err.errno, f"no I2C bus {self.config.i2c_bus}: {err.strerror}") from err
        try:
            driver = Mpu6050Driver(
                bus, self.config.address, self.config.accel_range_g, self.config.gyro_range_dps
            )
            driver.init(self.config.rate_hz)
        except OSError as err:
            bus.close()
            raise OSError(
                err.errno,
                f"no MPU-6050 at 0x{self.config.address:02x} on I2C bus "
                f"{self.config.i2c_bus}: {err.strerror or err}",
            ) from err
        except BaseException:
            bus.close()
            raise
        return driver

    async def _sample(self, driver: Mpu6050Driver, loop: asyncio.AbstractEventLoop) -> str:
        """Run the sampling thread until it gives up (returns why) or we are cancelled."""
        failed: asyncio.Future[str] = loop.create_future()
        self._failed = failed
        stop = threading.Event()
        thread = threading.Thread(
            target=self._thread_main,
            args=(driver, stop, loop, failed),
            name="imu-sampler",
            daemon=True,  # a read hung in the kernel must not keep the daemon from exiting
        )
        thread.start()
        try:
            return await failed
        finally:
            # The thread sees ``stop`` within one period and closes the bus itself on its way
            # out: joining here would block the loop for as long as a hung I2C read lasts.
            stop.set()
            self._failed = None

    def _thread_main(
        self,
        driver: Mpu6050Driver,
        stop: threading.Event,
        loop: asyncio.AbstractEventLoop,
        failed: asyncio.Future[str],
    ) -> None:
        """The sampling thread: reads at ``rate_hz`` on a steady clock, hands over batches.

        Whatever ends it is reported through ``failed`` (an IMU error, then a restart): a
        thread dying quietly would leave a frozen attitude reported as healthy."""
        try:
            self._sample_until(driver, stop, loop, failed)
            if not stop.is_set():
                self._to_loop(loop, _set_result, failed, "sampler ended unexpectedly")
        except BaseException as err:  # the thread's boundary: nothing may end it unreported
            _LOGGER.error("IMU sampler failed", exc_info=True)
            self._to_loop(loop, _set_result, failed, f"sampler failed: {type(err).__name__}: {err}")
        finally:
            driver.bus.close()

    def _sample_until(
        self,
        driver: Mpu6050Driver,
        stop: threading.Event,
        loop: asyncio.AbstractEventLoop,
        failed: asyncio.Future[str],
    ) -> None:
        if self.config.fifo:
            self._drain_fifo_until(driver, stop, loop, failed)
            return
        period = 1.0 / self.config.rate_hz
        per_batch = max(1, round(BATCH_SECONDS / period))
        # Raw bytes and times only: the thread holds the GIL as briefly as it can; the
        # conversion runs on the loop with the fusion.
        batch: list[tuple[float, list[int]]] = []
        errors = 0
        in_a_row = 0
        due = time.monotonic()
        while not stop.is_set():
            try:
                raw = driver.read_raw()
                batch.append((time.monotonic(), raw))
                in_a_row = 0
            except OSError as err:
                errors += 1
                in_a_row += 1
                if in_a_row >= MAX_CONSECUTIVE_ERRORS:
                    self._to_loop(loop, self._on_batch, driver, batch, errors)
                    self._to_loop(loop, _set_result, failed, f"I2C read failed: {err}")
                    return
            if len(batch) >= per_batch or (errors and in_a_row == 1):
                self._to_loop(loop, self._on_batch, driver, batch, errors)
                batch, errors = [], 0
            due += period
            delay = due - time.monotonic()
            if delay < -period:  # fell behind (a stalled bus): skip, never burst
                due = time.monotonic()
                delay = 0.0
            # time.sleep, not stop.wait(delay): a timed Event.wait costs ~40 % more CPU per
            # wake-up (Condition machinery); stop is seen within one period.
            time.sleep(delay if delay > 0 else 0)

    def _drain_fifo_until(
        self,
        driver: Mpu6050Driver,
        stop: threading.Event,
        loop: asyncio.AbstractEventLoop,
        failed: asyncio.Future[str],
    ) -> None:
        """FIFO mode: wake ~10 times a second, hand over what the chip queued meanwhile."""
        # Wake before the FIFO is half full, whatever the rate (at 1 kHz it fills in 85 ms).
        interval = min(BATCH_SECONDS, FIFO_SIZE // FIFO_SAMPLE // 2 * driver.sample_period)
        clock = SampleClock(driver.sample_period)
        errors = overflows = in_a_row = 0
        restart = True
        temperature: float | None = None
        temperature_due = 0.0
        due = time.monotonic()
        while not stop.is_set():
            data = b""
            start = 0.0
            try:
                if restart:
                    driver.fifo_start()
                    clock.reset()
                    restart = False
                if time.monotonic() >= temperature_due:
                    temperature = driver.read_temperature()
                    temperature_due = time.monotonic() + TEMPERATURE_INTERVAL
                counted_at = time.monotonic()
                count, flagged = driver.fifo_count()
                if fifo_overflowed(count, flagged):
                    # Samples were lost and the rest may not start on a sample: start over.
                    overflows += 1
                    restart = True
                elif count:
                    samples = count // FIFO_SAMPLE
                    data = driver.fifo_read(samples)
                    start = clock.place(samples, counted_at)
                in_a_row = 0
            except OSError as err:
                errors += 1
                in_a_row += 1
                restart = True  # a transfer cut short leaves the FIFO's alignment unknown
                if in_a_row >= MAX_CONSECUTIVE_ERRORS:
                    batch = FifoBatch(start, data, temperature, errors, overflows)
                    self._to_loop(loop, self._on_fifo_batch, driver, batch)
                    self._to_loop(loop, _set_result, failed, f"I2C read failed: {err}")
                    return
            if data or errors or overflows or temperature is not None:
                batch = FifoBatch(start, data, temperature, errors, overflows)
                self._to_loop(loop, self._on_fifo_batch, driver, batch)
                errors = overflows = 0
                temperature = None
            due += interval
            delay = due - time.monotonic()
            if delay < -interval:  # fell behind (a stalled bus): the FIFO holds the samples
                due = time.monotonic()
                delay = 0.0
            time.sleep(delay if delay > 0 else 0)

    @staticmethod
    def _to_loop(loop: asyncio.AbstractEventLoop, callback: Callable[..., Any], *args: Any) -> None:
        try:
            loop.call_soon_threadsafe(callback, *args)
        except RuntimeError:  # the loop is closing: nobody is listening any more
            pass

    # ------------------------------------------------------------------ on the loop

    def _on_batch(
        self, driver: Mpu6050Driver, batch: list[tuple[float, list[int]]], errors: int
    ) -> None:
        """Convert, fuse and publish a batch; must run on the event loop."""
        self.read_errors += errors
        samples = [driver.convert(when, bytes(raw)) for when, raw in batch]
        if samples:
            self.temperature_c = samples[-1].temperature_c
        self._fuse(samples)

    def _on_fifo_batch(self, driver: Mpu6050Driver, batch: FifoBatch) -> None:
        """FIFO mode's batch: convert, fuse sample by sample, publish; runs on the loop."""
        self.read_errors += batch.errors
        self.fifo_overflows += batch.overflows
        if batch.temperature_c is not None:
            self.temperature_c = batch.temperature_c
        if not batch.data:
            return
        samples = driver.convert_fifo(batch.start, batch.data, self.temperature_c or 0.0)
        self._fuse(samples)

    def _fuse(self, samples: list[Sample]) -> None:
        bias = self.gyro_bias
        for sample in samples:
            when = sample.time
            dt = 0.0 if self._last_time is None else when - self._last_time
            self._last_time = when
            if bias.add(sample.gyro_rad_s):
                self._calibrated(bias)
            gyro = bias.correct(sample.gyro_rad_s)
            self.filter.update(gyro, sample.accel_mps2, min(dt, 0.1))
        self.samples += len(samples)
        if not samples:
            return
        now = samples[-1].time
        if now - self._last_attitude_at >= ATTITUDE_INTERVAL * 0.9:
            self._last_attitude_at = now
            w, x, y, z = self.filter.q
            roll, pitch, yaw = euler_deg(self.filter.q)
            self.attitude = Attitude(w, x, y, z, roll, pitch, yaw, stamp=now)  # its sample's time
            self.bus.publish(topics.ATTITUDE, self.attitude)

    def _calibrated(self, bias: GyroBias) -> None:
        if bias.measured:
            _LOGGER.info(
                "IMU: gyro zero-rate offset %s deg/s",
                ", ".join(f"{math.degrees(v):+.2f}" for v in bias.offset),
            )
            # Start over from gravity: what was integrated with the offset is wrong.
            self.filter.reset()
        else:
            _LOGGER.warning("IMU: never still at start; gyro offset not measured (yaw drifts)")

    def _set_error(self, error: str, *, log: bool) -> None:
        self.error = error
        if log:
            _LOGGER.warning("IMU: %s; retrying", error)
        else:
            _LOGGER.debug("IMU: %s; retrying", error)
        self._publish_status()

    def status(self) -> ImuStatus:
        return ImuStatus(
            ok=not self.error and self.samples > 0,
            error=self.error,
            temperature_c=None if self.temperature_c is None else round(self.temperature_c, 2),
            samples=self.samples,
            read_errors=self.read_errors,
            calibrated=self.gyro_bias.measured,
            fifo_overflows=self.fifo_overflows,
        )

    def _publish_status(self) -> None:
        status = self.status()
        if status != self._status:
            self._status = status
            self.bus.publish(topics.IMU_STATUS, status)

    async def _status_loop(self) -> None:
        while True:
            await asyncio.sleep(STATUS_INTERVAL)
            self._publish_status()


def _close_opened(opening: asyncio.Future[Mpu6050Driver]) -> None:
    if not opening.cancelled() and opening.exception() is None:
        opening.result().bus.close()


def _set_result(future: asyncio.Future[str], reason: str) -> None:
    if not future.done():
        future.set_result(reason)


async def async_setup(ctx: PlatformContext) -> None:
    if not ctx.config.imu.enabled:
        return
    reader = ImuReader(ctx.bus, ctx.config.imu, ctx.sim.i2c_bus)  # the emulated chip in --sim
    ctx.capabilities.register(
        "imu",
        lambda: {
            "device": "MPU-6050",
            "i2c_bus": ctx.config.imu.i2c_bus,
            "address": ctx.config.imu.address,
            "rate_hz": ctx.config.imu.rate_hz,
            "fifo": ctx.config.imu.fifo,
        },
    )
    ctx.supervisor.start(reader)
