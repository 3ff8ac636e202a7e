"""Simulated u-blox NEO-6M: NMEA for the simulated vehicle's pose, on a pseudo-terminal.

Like the receiver (hardware.md): a few ``$GPTXT`` banner lines at power-up, then once per epoch
(``gps.sim_rate_hz``, 1-10; the NEO-6M defaults to 1 Hz) RMC, VTG, GGA and GSA with ``$GP``
talker IDs, positions with 5 decimals of minutes, HDOP about 1 and 8-10 satellites. The real
GPS reader opens the pty unchanged (``ctx.gps_port`` in --sim). A pty has no baud rate: at
10 Hz a real NEO-6M needs 38400 baud or more for these four sentences, 9600 only carries about
3 epochs a second; and the NEO-6M's data sheet gives 5 Hz as its highest navigation rate, so
10 Hz here is a stress setting (twice the sentences the real receiver can send).

The position error is the receiver's, as a NEO-6M makes it: 2.5 m CEP (the data sheet's figure,
GPS without SBAS, open sky), i.e. 2.1 m standard deviation on each horizontal axis, and slow:
a receiver's navigation filter smooths its output, so the error wanders over minutes with no
epoch-to-epoch jitter to speak of (in ``testdata/nmea/ublox-8.log`` a standing u-blox receiver's
fix moves 0.12 m a second, in steps that are positively correlated). A Gauss-Markov process
with a 5 minute time constant gives that: over one lap of a patrol it is nearly a constant
offset that no filter on the robot can see, because the receiver is the only absolute reference.
Speed and course over ground come from the Doppler shift, not from positions: accurate to
about 0.1 m/s whatever the position error (the data sheet's velocity accuracy).

That error model is a :class:`ReceiverErrors` profile: ``NEO_6M`` (the default, the rover's
receiver) or ``RTK``, a corrected receiver of the u-blox ZED-F9P class, for what the platform
achieves when the receiver allows it (``bench_patrol``); the sentences stay the NEO-6M's.

The UART of a receiver never blocks: when nobody reads the pty and its buffer is full, the
epoch is dropped (counted in ``line.overruns``), as bytes sent to an unplugged cable are lost.
"""

from __future__ import annotations

import asyncio
import datetime as dt
import logging
import math
import random
import sys
from collections.abc import Callable
from dataclasses import dataclass

from brasidas.actor import Actor, Supervisor
from brasidas.bus import Bus
from brasidas.codecs.nmea import sentence
from brasidas.config import GpsSection, PlatformConfig
from platformd.sim.pty_line import PtyLine
from platformd.sim.vehicle import EARTH_RADIUS_M, Pose, VehicleModel, vehicle_for

_LOGGER = logging.getLogger(__name__)

BANNER = (
    "GPTXT,01,01,02,u-blox ag - www.u-blox.com",
    "GPTXT,01,01,02,HW  UBX-G60xx  00040007 FF7FFFFFp",
    "GPTXT,01,01,02,ROM CORE 7.03 (45969) Mar 17 2011 16:18:34",
    "GPTXT,01,01,02,ANTSUPERV=AC SD PDoS SR",
    "GPTXT,01,01,02,ANTSTATUS=OK",
)
GEOID_SEPARATION_M = 34.0
KNOTS_PER_MPS = 3600.0 / 1852.0
NOISE_SIGMA_M = 2.1
"""Steady-state standard deviation of the error on each horizontal axis: 2.5 m CEP (NEO-6M)."""
NOISE_CORRELATION_S = 300.0
"""Time constant of the error's wander: GPS error is slow (minutes), not white."""
VELOCITY_SIGMA_MPS = 0.05
"""Doppler velocity noise on each horizontal axis (data sheet: 0.1 m/s, 50 %)."""


@dataclass(frozen=True)
class ReceiverErrors:
    """A receiver's position error: a Gauss-Markov process on each horizontal axis."""

    sigma_m: float
    """Steady-state standard deviation on each horizontal axis (altitude: 1.5 times it)."""
    correlation_s: float
    """Time constant of its wander."""
    minute_decimals: int = 5
    """Decimals of the minutes in the NMEA positions (5: 1.9 cm of latitude)."""


NEO_6M = ReceiverErrors(NOISE_SIGMA_M, NOISE_CORRELATION_S)
"""The u-blox NEO-6M: 2.5 m CEP, GPS without SBAS, open sky (its data sheet)."""
RTK = ReceiverErrors(0.02, 60.0, minute_decimals=7)
"""An RTK-corrected receiver, u-blox ZED-F9P class: its data sheet gives RTK horizontal
accuracy 0.01 m + 1 ppm CEP (open sky, fixed ambiguities, a base within ~10 km: 0.02 m CEP,
taken here as 0.02 m per axis, a little worse), at up to 20 Hz; its error is multipath,
slow over tens of seconds; high-precision NMEA (CFG-NMEA-HIGHPREC) prints 7 decimals of
minutes (0.2 mm), 5 would round to 1.9 cm."""
RECEIVERS = {"neo6m": NEO_6M, "rtk": RTK}
"""The profiles by their ``sim.gps_receiver`` name."""


class NmeaGenerator:
    """Sans-IO: a pose and a UTC time in, one epoch of NEO-6M sentences out."""

    def __init__(self, rng: random.Random | None = None, errors: ReceiverErrors = NEO_6M) -> None:
        self.rng = rng or random.Random()
        self.errors = errors
        self._north_m = self.rng.gauss(0.0, errors.sigma_m)
        self._east_m = self.rng.gauss(0.0, errors.sigma_m)
        self._alt_m = self.rng.gauss(0.0, 1.5 * errors.sigma_m)
        self._last: float | None = None
        self.satellites = self.rng.randint(8, 10)
        self.hdop = round(self.rng.uniform(0.9, 1.1), 2)

    @property
    def error(self) -> tuple[float, float]:
        """The position error of the last epoch: metres east and north of the truth."""
        return (self._east_m, self._north_m)

    def banner(self) -> bytes:
        return b"".join(sentence(line) for line in BANNER)

    def epoch(self, pose: Pose, utc: dt.datetime) -> bytes:
        """RMC, VTG, GGA and GSA for ``pose`` at ``utc`` (the error model advances with time)."""
        self._wander(utc.timestamp())
        lat0 = math.radians(pose.latitude)
        latitude = pose.latitude + math.degrees(self._north_m / EARTH_RADIUS_M)
        longitude = pose.longitude + math.degrees(self._east_m / (EARTH_RADIUS_M * math.cos(lat0)))
        altitude = pose.altitude_m + self._alt_m
        # Velocity over ground from the Doppler shift: its own small noise, per axis.
        heading = math.radians(pose.heading_deg)
        v_east = pose.speed_mps * math.sin(heading) + self.rng.gauss(0.0, VELOCITY_SIGMA_MPS)
        v_north = pose.speed_mps * math.cos(heading) + self.rng.gauss(0.0, VELOCITY_SIGMA_MPS)
        speed = math.hypot(v_east, v_north)
        knots = speed * KNOTS_PER_MPS
        # u-blox leaves the course empty while (nearly) stationary.
        course_deg = math.degrees(math.atan2(v_east, v_north)) % 360.0
        course = f"{course_deg:.2f}" if speed > 0.1 else ""
        # Fields, not strftime ({utc:%H%M%S}): CPython's strftime keeps a little of each
        # distinct result alive, a steady growth over a long --sim run (issue 10, defect 8).
        hhmmss = f"{utc.hour:02d}{utc.minute:02d}{utc.second:02d}.{utc.microsecond // 10000:02d}"
        ddmmyy = f"{utc.day:02d}{utc.month:02d}{utc.year % 100:02d}"
        decimals = self.errors.minute_decimals
        lat, ns = _ddmm(latitude, 2, decimals), "N" if latitude >= 0 else "S"
        lon, ew = _ddmm(longitude, 3, decimals), "E" if longitude >= 0 else "W"
        svs = [3, 6, 7, 9, 14, 16, 19, 21, 22, 26, 27, 31][: self.satellites]
        sv_fields = ",".join([f"{sv:02d}" for sv in svs] + [""] * (12 - len(svs)))
        pdop, vdop = round(self.hdop * 1.6, 2), round(self.hdop * 1.3, 2)
        return b"".join(
            (
                sentence(
                    f"GPRMC,{hhmmss},A,{lat},{ns},{lon},{ew},{knots:.3f},{course},{ddmmyy},,,A"
                ),
                sentence(f"GPVTG,{course},T,,M,{knots:.3f},N,{speed * 3.6:.3f},K,A"),
                sentence(
                    f"GPGGA,{hhmmss},{lat},{ns},{lon},{ew},1,{self.satellites:02d},"
                    f"{self.hdop:.2f},{altitude:.1f},M,{GEOID_SEPARATION_M:.1f},M,,"
                ),
                sentence(f"GPGSA,A,3,{sv_fields},{pdop:.2f},{self.hdop:.2f},{vdop:.2f}"),
            )
        )

    def _wander(self, now: float) -> None:
        dt_s = 1.0 if self._last is None else max(0.0, now - self._last)
        self._last = now
        keep = math.exp(-dt_s / self.errors.correlation_s)
        kick = self.errors.sigma_m * math.sqrt(1.0 - keep * keep)
        self._north_m = self._north_m * keep + self.rng.gauss(0.0, kick)
        self._east_m = self._east_m * keep + self.rng.gauss(0.0, kick)
        self._alt_m = self._alt_m * keep + self.rng.gauss(0.0, 1.5 * kick)
        if self.rng.random() < 0.02 * dt_s:  # a satellite rises or sets now and then
            self.satellites = min(10, max(8, self.satellites + self.rng.choice((-1, 1))))
            self.hdop = round(min(1.3, max(0.8, 1.0 + (9 - self.satellites) * 0.08)), 2)


class GpsSimulator(Actor):
    """Writes the generator's sentences to a pty at ``rate_hz`` (the slave is ``path``)."""

    name = "sim:gps"

    def __init__(
        self,
        bus: Bus,
        vehicle: VehicleModel,
        rate_hz: float = 1.0,
        *,
        generator: NmeaGenerator | None = None,
        utcnow: Callable[[], dt.datetime] = lambda: dt.datetime.now(dt.UTC),
    ) -> None:
        super().__init__(bus)
        self.vehicle = vehicle
        self.rate_hz = min(10.0, max(1.0, rate_hz))
        self.generator = generator or NmeaGenerator()
        self._utcnow = utcnow
        self.line = PtyLine("simulated GPS")
        self.path = self.line.path
        self.epochs = 0

    async def run(self) -> None:
        try:
            await self._serve()
        except asyncio.CancelledError:
            # Closed on cancellation, not in a stop hook: stop hooks run before the reader is
            # cancelled, and it would log the vanished port on every shutdown.
            self.close()
            raise

    async def _serve(self) -> None:
        period = 1.0 / self.rate_hz
        self.line.write(self.generator.banner())
        # Epochs on the UTC grid, like a receiver's (hhmmss.00 at 1 Hz, .10 .20 at 10 Hz).
        while True:
            now = self._utcnow().timestamp()
            tick = math.floor(now / period) + 1
            await asyncio.sleep(max(0.0, tick * period - now))
            centis = round(tick * period * 100)
            utc = dt.datetime.fromtimestamp(centis // 100, dt.UTC)
            utc = utc.replace(microsecond=(centis % 100) * 10_000)
            self.epochs += 1
            self.line.write(self.generator.epoch(self.vehicle.pose(), utc))

    def close(self) -> None:
        """Close the pty (idempotent)."""
        self.line.close()


def _ddmm(degrees: float, width: int, decimals: int) -> str:
    """``ddmm.mmmmm`` (``dddmm.mmmmm`` for longitude) as the NEO-6M prints it."""
    degrees = abs(degrees)
    whole = int(degrees)
    minutes = round((degrees - whole) * 60.0, decimals)
    if minutes >= 60.0:
        whole, minutes = whole + 1, 0.0
    return f"{whole:0{width}d}{minutes:0{decimals + 3}.{decimals}f}"


def start_simulator(
    bus: Bus,
    supervisor: Supervisor,
    gps: GpsSection,
    vehicle: VehicleModel,
    receiver: ReceiverErrors = NEO_6M,
) -> GpsSimulator | None:
    """In ``--sim``: a simulated receiver with ``receiver``'s error on a pty, unless
    ``gps.port`` names another device."""
    if gps.port != GpsSection().port:
        # ``--set gps.port=...`` names a pty or a real receiver: read that instead.
        _LOGGER.info("gps.port is %s: no simulated receiver", gps.port)
        return None
    simulator = GpsSimulator(
        bus, vehicle, gps.sim_rate_hz, generator=NmeaGenerator(errors=receiver)
    )
    supervisor.start(simulator)
    return simulator


async def serve(config: PlatformConfig) -> None:
    """``brasidas-platform simulate gps``: the pty path on stdout's first line, then serve."""
    generator = NmeaGenerator(errors=RECEIVERS[config.sim.gps_receiver])
    simulator = GpsSimulator(
        Bus(), vehicle_for(config), config.gps.sim_rate_hz, generator=generator
    )
    try:
        sys.stdout.write(simulator.path + "\n")
        sys.stdout.flush()
        await simulator.run()
    finally:
        simulator.close()
