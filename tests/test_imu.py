"""IMU: Madgwick filter, the emulated MPU-6050 register map, the driver and actor against it."""

from __future__ import annotations

import asyncio
import contextlib
import math
import struct
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from typing import Any

import pytest

from brasidas import topics
from brasidas.bus import Bus
from brasidas.codecs.telemetry_schema import Attitude as AttitudeSection
from brasidas.config import ImuSection, PlatformConfig
from brasidas.drivers.mpu6050 import Mpu6050Driver, SampleClock, fifo_overflowed
from brasidas.madgwick import Madgwick, euler_deg, from_euler
from brasidas.messages import Attitude, ImuStatus
from platformd.app import PlatformDaemon
from platformd.imu import GyroBias, ImuReader
from platformd.sim.mpu6050 import (
    ACCEL_CONFIG,
    CONFIG,
    DATA_START,
    FIFO_COUNTH,
    FIFO_EN,
    FIFO_R_W,
    GYRO_CONFIG,
    INT_ENABLE,
    INT_STATUS,
    PWR_MGMT_1,
    SMPLRT_DIV,
    USER_CTRL,
    WHO_AM_I,
    EmulatedI2CBus,
    Motion,
    Mpu6050,
)
from tests.conftest import quiet_platform_config, wait_until

G = 9.80665
LEVEL = Motion(accel_mps2=(0.0, 0.0, G), gyro_rad_s=(0.0, 0.0, 0.0), temperature_c=25.0)


# --------------------------------------------------------------------------- Madgwick


def test_madgwick_static_level_stays_level() -> None:
    fusion = Madgwick(beta=0.1)
    for _ in range(500):
        fusion.update((0.0, 0.0, 0.0), (0.0, 0.0, G), 0.01)
    roll, pitch, yaw = euler_deg(fusion.q)
    assert abs(roll) < 0.01
    assert abs(pitch) < 0.01
    assert abs(yaw) < 0.01


def test_madgwick_converges_to_gravity_from_a_wrong_start() -> None:
    fusion = Madgwick(beta=0.2, q=from_euler(math.radians(20), math.radians(-10), 0.0))
    fusion.initialized = True  # skip the first-sample snap: exercise the gradient step
    for _ in range(2000):
        fusion.update((0.0, 0.0, 0.0), (0.0, 0.0, G), 0.01)
    roll, pitch, _ = euler_deg(fusion.q)
    assert abs(roll) < 0.5
    assert abs(pitch) < 0.5


def test_madgwick_first_sample_sets_tilt() -> None:
    roll = math.radians(15)
    fusion = Madgwick()
    # Rolled right side down by 15 deg: gravity appears on +y and z.
    fusion.update((0.0, 0.0, 0.0), (0.0, G * math.sin(roll), G * math.cos(roll)), 0.01)
    got_roll, got_pitch, _ = euler_deg(fusion.q)
    assert got_roll == pytest.approx(15.0, abs=0.01)
    assert got_pitch == pytest.approx(0.0, abs=0.01)


def test_madgwick_integrates_yaw_rate_counter_clockwise() -> None:
    fusion = Madgwick(beta=0.05)
    rate = math.radians(30)
    for _ in range(300):  # 3 s at 30 deg/s
        fusion.update((0.0, 0.0, rate), (0.0, 0.0, G), 0.01)
    _, _, yaw = euler_deg(fusion.q)
    assert yaw == pytest.approx(90.0, abs=0.5)


def test_euler_round_trip() -> None:
    q = from_euler(math.radians(10), math.radians(-20), math.radians(135))
    assert euler_deg(q) == pytest.approx((10.0, -20.0, 135.0), abs=1e-9)


# --------------------------------------------------------------------------- the emulated chip


def test_chip_sleeps_until_woken_and_scales() -> None:
    chip = Mpu6050(lambda at: LEVEL)
    bus = EmulatedI2CBus({0x68: chip})
    assert bus.read_byte_data(0x68, WHO_AM_I) == 0x68
    assert bus.read_byte_data(0x68, PWR_MGMT_1) == 0x40  # asleep after power-on
    assert bus.read_i2c_block_data(0x68, DATA_START, 14) == [0] * 14
    bus.write_byte_data(0x68, PWR_MGMT_1, 0x01)
    raw = bytes(bus.read_i2c_block_data(0x68, DATA_START, 14))
    assert raw[4:6] == (16384).to_bytes(2, "big")  # +1 g on z at +-2 g
    temperature = int.from_bytes(raw[6:8], "big", signed=True)
    assert temperature / 340 + 36.53 == pytest.approx(25.0, abs=0.01)
    bus.write_byte_data(0x68, ACCEL_CONFIG, 2 << 3)  # +-8 g
    raw = bytes(bus.read_i2c_block_data(0x68, DATA_START, 14))
    assert int.from_bytes(raw[4:6], "big") == 4096
    bus.write_byte_data(0x68, PWR_MGMT_1, 0x80)  # device reset: asleep again, registers cleared
    assert bus.read_byte_data(0x68, PWR_MGMT_1) == 0x40
    assert bus.read_byte_data(0x68, ACCEL_CONFIG) == 0
    with pytest.raises(OSError):
        bus.read_byte_data(0x69, WHO_AM_I)  # nothing at AD0 high


def test_driver_reads_si_units_through_the_chip() -> None:
    spin = Motion((0.5, -0.25, G), (0.0, 0.0, math.radians(100.0)), 30.0)
    chip = Mpu6050(lambda at: spin)
    driver = Mpu6050Driver(EmulatedI2CBus({0x68: chip}), 0x68, 4, 500)
    driver.init(100.0)
    assert chip.registers[GYRO_CONFIG] == 1 << 3
    assert chip.registers[ACCEL_CONFIG] == 1 << 3
    sample = driver.read()
    assert sample.accel_mps2 == pytest.approx((0.5, -0.25, G), abs=0.005)
    assert math.degrees(sample.gyro_rad_s[2]) == pytest.approx(100.0, abs=0.02)
    assert sample.temperature_c == pytest.approx(30.0, abs=0.01)


class Turntable:
    """Still for ``delay`` s after the first read, then yaws at ``rate`` deg/s (CCW) for
    ``total`` degrees; the chip's gyro reads ``bias`` deg/s more on each axis.

    ``averaged``: the gyro reads the mean rate since the previous read, so the yaw summed over
    the reads is the turn whenever they come. Read at real times (burst mode), an instantaneous
    step of 45 °/s is missed or doubled for as long as a read is late at either edge: a
    starved CPU's late reads made a 5° error (a timing effect, not the fusion under test)."""

    def __init__(
        self,
        rate: float,
        total: float,
        clock: Callable[[], float],
        delay: float = 0.0,
        bias: tuple[float, float, float] = (0.0, 0.0, 0.0),
        averaged: bool = False,
    ) -> None:
        self.rate, self.total, self.clock, self.delay = rate, total, clock, delay
        self.bias = tuple(math.radians(b) for b in bias)
        self.averaged = averaged
        self.start: float | None = None
        self._previous: float | None = None

    def turn_in(self, seconds: float) -> None:
        """Start the turn ``seconds`` from now (set ``delay=math.inf`` to wait for this)."""
        assert self.start is not None, "not read yet"
        self.delay = self.clock() - self.start + seconds

    def _turned(self, at: float) -> float:
        """Degrees turned by ``at``."""
        assert self.start is not None
        return min(self.total, max(0.0, (at - self.start - self.delay) * self.rate))

    def done(self) -> bool:
        return (
            self.start is not None
            and self.clock() - self.start > self.delay + self.total / self.rate
        )

    def __call__(self, now: float) -> Motion:
        if self.start is None:
            self.start = now
        previous, self._previous = self._previous, now
        if self.averaged and previous is not None and now > previous:
            rate = math.radians((self._turned(now) - self._turned(previous)) / (now - previous))
        else:
            elapsed = now - self.start - self.delay
            turning = 0.0 <= elapsed and elapsed * self.rate < self.total
            rate = math.radians(self.rate) if turning else 0.0
        bx, by, bz = self.bias
        return Motion((0.0, 0.0, G), (bx, by, bz + rate), 28.0)


def test_known_rotation_gives_yaw_within_two_degrees() -> None:
    now = [0.0]
    chip = Mpu6050(Turntable(45.0, 90.0, lambda: now[0]), clock=lambda: now[0])
    driver = Mpu6050Driver(EmulatedI2CBus({0x68: chip}), 0x68, 2, 250)
    driver.init(100.0)
    fusion = Madgwick(0.05)
    last = None
    for k in range(300):  # 3 s at 100 Hz; the turn lasts 2 s
        now[0] = k / 100
        raw = bytes(driver.bus.read_i2c_block_data(0x68, DATA_START, 14))
        sample = driver.convert(now[0], raw)
        fusion.update(sample.gyro_rad_s, sample.accel_mps2, 0.0 if last is None else now[0] - last)
        last = now[0]
    _, _, yaw = euler_deg(fusion.q)
    assert yaw == pytest.approx(90.0, abs=2.0)


class Ramp:
    """Each sample's gyro z tells its time: 1 deg/s per ms since 0 (wraps every 250 ms)."""

    def __call__(self, at: float) -> Motion:
        return Motion((0.0, 0.0, G), (0.0, 0.0, math.radians((at * 1000) % 250)), 25.0)


def fifo_chip(now: list[float], source: Any = None) -> tuple[Mpu6050, EmulatedI2CBus]:
    chip = Mpu6050(source or (lambda at: LEVEL), clock=lambda: now[0])
    bus = EmulatedI2CBus({0x68: chip})
    bus.write_byte_data(0x68, PWR_MGMT_1, 0x01)
    bus.write_byte_data(0x68, CONFIG, 0x03)  # DLPF on: 1 kHz gyro output rate
    bus.write_byte_data(0x68, SMPLRT_DIV, 9)  # 100 Hz
    bus.write_byte_data(0x68, FIFO_EN, 0x78)
    bus.write_byte_data(0x68, USER_CTRL, 0x40)
    return chip, bus


def fifo_count(bus: EmulatedI2CBus) -> int:
    return int.from_bytes(bytes(bus.read_i2c_block_data(0x68, FIFO_COUNTH, 2)), "big")


def test_fifo_fills_at_the_sample_rate_and_pops_on_read() -> None:
    now = [10.0]
    _, bus = fifo_chip(now, Ramp())
    assert fifo_count(bus) == 0
    now[0] += 0.0995
    assert fifo_count(bus) == 9 * 12  # ticks at +10 ms, +20 ms ... +90 ms
    now[0] += 0.001
    assert fifo_count(bus) == 10 * 12
    first = bytes(bus.read_i2c_block_data(0x68, FIFO_R_W, 24))  # a burst stays on FIFO_R_W
    assert fifo_count(bus) == 8 * 12
    ax, ay, az, gx, gy, gz = struct.unpack(">6h", first[:12])
    assert (ax, ay, az, gx, gy) == (0, 0, 16384, 0, 0)  # accel first, then gyro: register order
    assert gz == 10 * 131  # sampled at its own tick, +10 ms, not at the read
    assert struct.unpack(">6h", first[12:])[5] == 20 * 131
    rest = b"".join(bytes(bus.read_i2c_block_data(0x68, FIFO_R_W, 24)) for _ in range(4))
    assert [struct.unpack(">6h", rest[k : k + 12])[5] for k in range(0, 96, 12)] == [
        round(ms * 131) for ms in range(30, 110, 10)
    ]
    assert fifo_count(bus) == 0
    assert bus.read_i2c_block_data(0x68, FIFO_R_W, 3) == [rest[-1]] * 3  # empty: last byte again
    # 8 kHz without the DLPF; FIFO_EN picks the record (here gyro z alone: 2 bytes).
    bus.write_byte_data(0x68, CONFIG, 0x00)
    bus.write_byte_data(0x68, SMPLRT_DIV, 7)  # 1 kHz
    bus.write_byte_data(0x68, FIFO_EN, 0x10)
    now[0] += 0.0105  # the tick already due at the old rate, then 1 kHz
    queued = fifo_count(bus)
    now[0] += 0.010
    assert fifo_count(bus) == queued + 2 * 10
    # FIFO_RESET is ignored while FIFO_EN stays set, acts once it is clear, and self-clears.
    bus.write_byte_data(0x68, USER_CTRL, 0x44)
    assert fifo_count(bus) > 0
    bus.write_byte_data(0x68, USER_CTRL, 0x04)
    assert fifo_count(bus) == 0
    assert bus.read_byte_data(0x68, USER_CTRL) == 0
    now[0] += 1.0  # disabled: nothing queued
    assert fifo_count(bus) == 0
    bus.write_byte_data(0x68, PWR_MGMT_1, 0x40)  # asleep: nothing queued either
    bus.write_byte_data(0x68, USER_CTRL, 0x40)
    now[0] += 1.0
    assert fifo_count(bus) == 0


def test_fifo_overflow_drops_the_oldest_bytes_and_flags() -> None:
    now = [0.0]
    chip, bus = fifo_chip(now, Ramp())
    bus.write_byte_data(0x68, INT_ENABLE, 0x10)
    now[0] += 0.85  # 85 records: 1020 bytes, still whole
    assert fifo_count(bus) == 1020
    assert bus.read_byte_data(0x68, INT_STATUS) == 0
    now[0] += 0.02  # two more: 1044 bytes offered, the oldest 20 go
    assert fifo_count(bus) == 1024
    assert bus.read_byte_data(0x68, INT_STATUS) & 0x10
    assert bus.read_byte_data(0x68, INT_STATUS) == 0  # cleared by the read
    data = bytes(bus.read_i2c_block_data(0x68, FIFO_R_W, 32))
    # The head is now 20 bytes into the stream: mid-record (record 2's gyro y, then z).
    assert struct.unpack(">h", data[2:4])[0] == 20 * 131
    assert struct.unpack(">6h", data[4:16])[5] == 30 * 131  # record 3 whole after it
    now[0] += 100.0  # a long stall: the newest 1024 bytes only, computed without 10^4 records
    assert fifo_count(bus) == 1024
    assert bus.read_byte_data(0x68, INT_STATUS) & 0x10
    assert chip.overflows == 2
    bus.write_byte_data(0x68, USER_CTRL, 0x04)
    bus.write_byte_data(0x68, USER_CTRL, 0x40)
    assert fifo_count(bus) == 0


def test_driver_fifo_mode_through_the_chip() -> None:
    now = [5.0]
    spin = Motion((0.5, -0.25, G), (0.0, 0.0, math.radians(100.0)), 30.0)
    chip = Mpu6050(lambda at: spin, clock=lambda: now[0])
    driver = Mpu6050Driver(EmulatedI2CBus({0x68: chip}), 0x68, 4, 500)
    driver.init(100.0)
    driver.fifo_start()
    assert chip.registers[FIFO_EN] == 0x78
    assert chip.registers[USER_CTRL] == 0x40
    now[0] += 0.1001
    count, flagged = driver.fifo_count()
    assert (count, flagged) == (120, False)
    assert not fifo_overflowed(count, flagged)
    samples = driver.convert_fifo(1.0, driver.fifo_read(count // 12), 30.0)
    assert [s.time for s in samples] == pytest.approx([1.0 + k / 100 for k in range(10)])
    assert samples[3].accel_mps2 == pytest.approx((0.5, -0.25, G), abs=0.005)
    assert math.degrees(samples[3].gyro_rad_s[2]) == pytest.approx(100.0, abs=0.02)
    assert driver.read_temperature() == pytest.approx(30.0, abs=0.01)
    now[0] += 2.0
    assert fifo_overflowed(*driver.fifo_count())
    driver.fifo_start()
    assert driver.fifo_count() == (0, False)
    assert fifo_overflowed(1020, False) is False
    assert fifo_overflowed(1021, False) is True
    assert fifo_overflowed(1024, False) is True
    assert fifo_overflowed(0, True) is True


def test_sample_clock_evenly_spaced_and_kept_near_the_host() -> None:
    clock = SampleClock(0.01)
    assert clock.place(10, 1.0) == pytest.approx(0.91)  # the newest taken at the count
    assert clock.place(10, 1.1) == pytest.approx(1.01)  # continues, evenly spaced
    assert clock.place(10, 1.3) == pytest.approx(1.2)  # fell behind the window: nudged
    assert clock.place(10, 1.35) == pytest.approx(1.26)  # ran ahead of the count: held back


def test_known_rotation_through_the_fifo_within_two_degrees() -> None:
    now = [0.0]
    chip = Mpu6050(Turntable(45.0, 90.0, lambda: now[0]), clock=lambda: now[0])
    driver = Mpu6050Driver(EmulatedI2CBus({0x68: chip}), 0x68, 2, 250)
    driver.init(100.0)
    driver.fifo_start()
    clock = SampleClock(driver.sample_period)
    fusion = Madgwick(0.05)
    last = None
    for k in range(1, 31):  # 3 s, drained every 100 ms (a little late, as a thread would be)
        now[0] = k / 10 + 0.003
        count, flagged = driver.fifo_count()
        assert not fifo_overflowed(count, flagged)
        start = clock.place(count // 12, now[0])
        for sample in driver.convert_fifo(start, driver.fifo_read(count // 12), 25.0):
            dt = 0.0 if last is None else sample.time - last
            assert last is None or dt == pytest.approx(0.01)
            fusion.update(sample.gyro_rad_s, sample.accel_mps2, dt)
            last = sample.time
    _, _, yaw = euler_deg(fusion.q)
    assert yaw == pytest.approx(90.0, abs=2.0)


# --------------------------------------------------------------------------- the actor


class Recorder:
    def __init__(self, bus: Bus) -> None:
        self.attitudes: list[Attitude] = []
        self.statuses: list[ImuStatus] = []
        bus.subscribe(topics.ATTITUDE, self.attitudes.append)
        bus.subscribe(topics.IMU_STATUS, self.statuses.append)


@contextlib.asynccontextmanager
async def running(reader: ImuReader) -> AsyncIterator[ImuReader]:
    task = asyncio.create_task(reader.run(), name="test:imu")
    try:
        yield reader
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


class FaultyMotion:
    """A level chip whose emulation raises once when armed: not an OSError (a driver or
    conversion bug, a bus library raising something else)."""

    def __init__(self) -> None:
        self.armed = False

    def __call__(self, now: float) -> Motion:
        if self.armed:
            self.armed = False
            raise RuntimeError("emulated chip fault")
        return LEVEL


@pytest.mark.parametrize("fifo", [True, False], ids=["fifo", "burst"])
async def test_sampler_thread_failure_is_reported_and_sampling_restarts(fifo: bool) -> None:
    bus = Bus()
    seen = Recorder(bus)
    motion = FaultyMotion()
    chip = Mpu6050(motion)
    reader = ImuReader(bus, ImuSection(fifo=fifo), lambda number: EmulatedI2CBus({0x68: chip}))
    async with running(reader):
        await wait_until(lambda: reader.samples > 20)
        motion.armed = True
        # Reported as an IMU error on IMU_STATUS: not a frozen attitude that looks healthy.
        await wait_until(lambda: any("RuntimeError" in s.error for s in seen.statuses))
        failed = next(s for s in seen.statuses if "RuntimeError" in s.error)
        assert not failed.ok
        assert "emulated chip fault" in failed.error
        # The actor restarts the sampler (with backoff) and the attitude flows again.
        count = reader.samples
        await wait_until(lambda: reader.samples > count + 20)
        assert reader.status().ok
        assert reader.error == ""


@pytest.mark.parametrize("fifo", [True, False], ids=["fifo", "burst"])
async def test_actor_turn_through_emulated_chip(fifo: bool) -> None:
    bus = Bus()
    seen = Recorder(bus)
    # A chip with a real-looking zero-rate offset: uncorrected, it alone would add ~5 deg.
    # Still until the offset is measured (a condition: on a starved CPU the 100 samples of
    # calibrate_s take longer than any fixed delay), then a 2 s turn.
    table = Turntable(
        45.0, 90.0, time.monotonic, delay=math.inf, bias=(0.5, -0.8, 1.5), averaged=True
    )
    chip = Mpu6050(table)
    config = ImuSection(fifo=fifo)
    reader = ImuReader(bus, config, lambda number: EmulatedI2CBus({0x68: chip}))
    async with running(reader):
        await wait_until(lambda: reader.gyro_bias.measured, 15.0)
        table.turn_in(0.3)
        await wait_until(lambda: table.done(), 15.0)
        await asyncio.sleep(0.2)
        count = len(seen.attitudes)
        await wait_until(lambda: len(seen.attitudes) > count)
        await wait_until(lambda: bool(seen.statuses) and seen.statuses[-1].samples > 100)
    assert seen.attitudes[-1].yaw_deg == pytest.approx(90.0, abs=2.0)
    assert abs(seen.attitudes[-1].roll_deg) < 1.0
    assert abs(seen.attitudes[-1].pitch_deg) < 1.0
    status = seen.statuses[-1]
    assert status.ok
    assert status.error == ""
    assert status.read_errors == 0
    assert status.calibrated
    assert math.degrees(reader.gyro_bias.offset[2]) == pytest.approx(1.5, abs=0.05)
    assert status.temperature_c == pytest.approx(28.0, abs=0.01)
    # About 10 Hz of attitude for about 100 Hz of samples, not one per sample.
    assert len(seen.attitudes) < reader.samples / 5


async def test_fifo_overflow_is_detected_counted_and_recovered() -> None:
    bus = Bus()
    seen = Recorder(bus)
    skew = [0.0]
    chip = Mpu6050(lambda at: LEVEL, clock=lambda: time.monotonic() + skew[0])
    reader = ImuReader(bus, ImuSection(), lambda number: EmulatedI2CBus({0x68: chip}))
    async with running(reader):
        await wait_until(lambda: bool(seen.statuses) and seen.statuses[-1].ok)
        before, started = reader.samples, time.monotonic()
        skew[0] += 2.0  # the chip ran 2 s ahead of the reader: 200 samples for 85 places
        await wait_until(lambda: reader.fifo_overflows >= 1, 5.0)
        after = reader.samples
        await wait_until(lambda: reader.samples > after + 50, 5.0)  # draining again
        await wait_until(lambda: seen.statuses[-1].fifo_overflows >= 1, 5.0)
        elapsed = time.monotonic() - started
    assert chip.overflows >= 1
    assert reader.fifo_overflows == 1
    assert reader.read_errors == 0
    # What overflowed was dropped, not read: real time's samples plus at most one full FIFO.
    assert reader.samples - before < 100 * elapsed + 100
    assert seen.statuses[-1].ok
    assert seen.statuses[-1].fifo_overflows == 1
    assert abs(seen.attitudes[-1].roll_deg) < 1.0
    assert abs(seen.attitudes[-1].pitch_deg) < 1.0


async def test_wrong_who_am_i_is_an_error_then_recovers() -> None:
    bus = Bus()
    seen = Recorder(bus)
    chip = Mpu6050(lambda at: LEVEL, who_am_i=0x72)  # an MPU-9250-like part
    reader = ImuReader(bus, ImuSection(), lambda number: EmulatedI2CBus({0x68: chip}))
    async with running(reader):
        await wait_until(lambda: bool(seen.statuses) and "WHO_AM_I" in seen.statuses[-1].error)
        assert not seen.statuses[-1].ok
        assert "0x72" in seen.statuses[-1].error
        await asyncio.sleep(0.5)  # retried with backoff, never a crash
        chip.who_am_i = 0x68
        chip.reset()
        await wait_until(lambda: bool(seen.statuses) and seen.statuses[-1].ok, 10.0)
        await wait_until(lambda: bool(seen.attitudes))


async def test_missing_device_and_missing_bus_are_reported() -> None:
    bus = Bus()
    seen = Recorder(bus)
    reader = ImuReader(bus, ImuSection(), lambda number: EmulatedI2CBus({}))
    async with running(reader):
        await wait_until(lambda: bool(seen.statuses) and seen.statuses[-1].error != "")
    assert "no MPU-6050 at 0x68 on I2C bus 1" in seen.statuses[-1].error

    def no_bus(number: int) -> EmulatedI2CBus:
        raise FileNotFoundError(2, "No such file or directory", f"/dev/i2c-{number}")

    bus2 = Bus()
    seen2 = Recorder(bus2)
    async with running(ImuReader(bus2, ImuSection(i2c_bus=7), no_bus)):
        await wait_until(lambda: bool(seen2.statuses) and seen2.statuses[-1].error != "")
    assert seen2.statuses[-1].error.startswith("[Errno 2] no I2C bus 7")


async def test_device_vanishing_mid_run_is_reported_and_reopened() -> None:
    bus = Bus()
    seen = Recorder(bus)
    chip = Mpu6050(lambda at: LEVEL)
    devices = {0x68: chip}
    reader = ImuReader(bus, ImuSection(), lambda number: EmulatedI2CBus(devices))
    async with running(reader):
        await wait_until(lambda: bool(seen.statuses) and seen.statuses[-1].ok)
        del devices[0x68]  # a loose wire
        await wait_until(lambda: "I2C read failed" in seen.statuses[-1].error, 5.0)
        assert reader.read_errors >= 10
        devices[0x68] = chip
        await wait_until(lambda: seen.statuses[-1].ok, 10.0)


async def test_sim_platform_publishes_attitude(
    platform_factory: Callable[[PlatformConfig, bytes | None], Awaitable[PlatformDaemon]],
    fleet_key: bytes,
) -> None:
    config = quiet_platform_config("sim.enabled=true", "imu.enabled=true")
    daemon = await platform_factory(config, fleet_key)
    assert daemon.ctx.sim.i2c_bus is not None
    assert daemon.ctx.sim.mpu6050 is not None
    await wait_until(lambda: daemon.bus.last(topics.ATTITUDE) is not None, 10.0)

    def attitude() -> AttitudeSection:
        section = daemon.ctx.telemetry.build_one(AttitudeSection)
        assert isinstance(section, AttitudeSection)
        return section

    await wait_until(lambda: attitude().imu is not None and attitude().imu.temp_c is not None, 5.0)
    section = attitude()
    assert section.roll is not None
    assert abs(section.roll) < 2.0
    assert section.pitch is not None
    assert abs(section.pitch) < 2.0
    assert section.q is not None
    assert len(section.q) == 4
    assert section.age_ms is not None
    assert not section.stale
    imu = section.imu
    assert imu is not None
    assert imu.ok is True
    assert imu.error == ""
    assert imu.temp_c is not None
    assert 20.0 < imu.temp_c < 40.0


def test_gyro_offset_from_a_still_window_only() -> None:
    offset = math.radians(1.2)
    bias = GyroBias(100)
    moving = [(0.0, 0.0, offset + math.radians(10) * math.sin(k / 5)) for k in range(100)]
    assert not any(bias.add(g) for g in moving)  # a wobble: not still, measured later
    assert bias.attempts == 1
    assert not bias.done
    turning = [(0.0, 0.0, math.radians(30.0))] * 100  # steady, but far above any offset
    assert not any(bias.add(g) for g in turning)
    still = [(0.001 * (k % 3), 0.0, offset) for k in range(100)]
    assert [bias.add(g) for g in still][-1] is True
    assert bias.measured
    assert bias.offset[2] == pytest.approx(offset)
    assert bias.correct((0.0, 0.0, offset)) == pytest.approx((-0.001, 0.0, 0.0), abs=0.001)


def test_gyro_offset_gives_up_when_never_still() -> None:
    bias = GyroBias(10, max_attempts=3)
    results = [bias.add((0.0, 0.0, 0.1 * (k % 2))) for k in range(30)]
    assert results[-1] is True
    assert bias.done
    assert not bias.measured
    assert bias.offset == (0.0, 0.0, 0.0)
