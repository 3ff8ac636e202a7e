"""Simulated LDROBOT LD19/LD06/STL-27L: the real frames for the simulated world, on a pty.

The sensor turns at 10 Hz and sends 12 points a frame (:mod:`brasidas.codecs.ldlidar`), one
frame every 12 / (points per second): 2.7 ms for the LD19 (4,500 points/s), 0.56 ms for the
STL-27L (21,600 points/s). A pty does not pace bytes, so the simulator does: every 10 ms it
writes the frames whose time has come, cast in one batch from the vehicle's pose at that tick
(a scan taken while moving is skewed, as a real one is).

What it sees, ray-cast in the plane of the sensor (``lidar.height_m``):

- the area map's keep-outs (buildings; a keep-out the platform added for an obstacle it saw,
  id ``lidar:...``, is not a wall);
- ``sim.obstacles_file``: GeoJSON polygons and ``Point`` features with ``radius_m``, which the
  platform is never told about; ``"material": "glass"`` lets the beam through (the sensor's
  905 nm light passes clear glass), ``"reflectivity"`` (0-1, default 0.5) sets the intensity;
- ``sim.pedestrians``: 0.3 m discs walking back and forth at 1.2 m/s.

Its errors, after the data sheets' accuracy class: range noise of 10 mm (to 0.5 m) then 1.5 %
(taken as 2 sigma), quantised to the wire's millimetre; a few random dropouts that grow with
range and with low reflectivity; ambient light (``sim.lux``, sunlight ~100,000 lux) shortens
the reach (by up to 40 %) and thins the far returns, as users report outdoors.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import logging
import math
import random
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
import numpy.random  # NumPy imports it on first use: on the loop, in the first scan
from numpy.typing import NDArray
from shapely.geometry import MultiPolygon, Point, Polygon, shape

from brasidas.actor import Actor, Supervisor
from brasidas.autonomy.geo import LocalFrame
from brasidas.bus import Bus
from brasidas.codecs.ldlidar import POINTS_PER_FRAME, encode_frames
from brasidas.config import PlatformConfig
from brasidas.config.lidar import LidarSection
from platformd.lidar_models import MODELS, TEMPORARY_KEEPOUT_PREFIX
from platformd.sim.pty_line import PtyLine
from platformd.sim.vehicle import Pose, VehicleModel, vehicle_for

if TYPE_CHECKING:
    from brasidas.autonomy.areamap import AreaMap

_LOGGER = logging.getLogger(__name__)

TICK_S = 0.01
"""How often the simulator writes the frames that are due."""
PEDESTRIAN_RADIUS_M = 0.3
PEDESTRIAN_SPEED_MPS = 1.2
PEDESTRIAN_WALK_M = 10.0


class LidarWorld:
    """Walls (segments) and discs in the simulator's local frame (x east, y north, metres)."""

    def __init__(
        self,
        polygons: list[tuple[Polygon, float]],
        discs: list[tuple[float, float, float, float]],
        pedestrians: int = 0,
        rng: random.Random | None = None,
    ) -> None:
        segments: list[tuple[float, float, float, float, float]] = []
        for polygon, reflectivity in polygons:
            for ring in (polygon.exterior, *polygon.interiors):
                coords = list(ring.coords)
                segments += (
                    (x0, y0, x1, y1, reflectivity)
                    for (x0, y0), (x1, y1) in itertools.pairwise(coords)
                )
        self.segments: NDArray[np.float64] = np.array(segments, dtype=float).reshape(-1, 5)
        self.discs: NDArray[np.float64] = np.array(discs, dtype=float).reshape(-1, 4)
        """x, y, radius, reflectivity."""
        rng = rng or random.Random(1)
        walks = []
        for _ in range(pedestrians):
            distance, bearing = rng.uniform(6.0, 25.0), rng.uniform(0, 2 * math.pi)
            heading = rng.uniform(0, 2 * math.pi)
            walks.append(
                (
                    distance * math.cos(bearing),
                    distance * math.sin(bearing),
                    math.cos(heading),
                    math.sin(heading),
                    rng.uniform(0, 2 * PEDESTRIAN_WALK_M),
                )
            )
        self.walks: NDArray[np.float64] = np.array(walks, dtype=float).reshape(-1, 5)
        """Each pedestrian's start, direction and phase: back and forth along 10 m."""

    def pedestrians_at(self, now: float) -> NDArray[np.float64]:
        """The pedestrians' positions at ``now`` (seconds), as discs."""
        people: NDArray[np.float64] = self.pedestrians_over(np.array([now]))[0]
        return people

    def pedestrians_over(self, times: NDArray[np.float64]) -> NDArray[np.float64]:
        """The pedestrians at each of ``times``: discs, shaped (times, pedestrians, 4)."""
        walks = self.walks
        if not len(walks):
            return np.empty((len(times), 0, 4))
        travelled = (walks[:, 4] + times[:, None] * PEDESTRIAN_SPEED_MPS) % (2 * PEDESTRIAN_WALK_M)
        along = PEDESTRIAN_WALK_M - np.abs(travelled - PEDESTRIAN_WALK_M)  # a triangle wave
        people = np.empty((len(times), len(walks), 4))
        people[:, :, 0] = walks[:, 0] + walks[:, 2] * along
        people[:, :, 1] = walks[:, 1] + walks[:, 3] * along
        people[:, :, 2] = PEDESTRIAN_RADIUS_M
        people[:, :, 3] = 0.4
        return people

    def near(self, x: float, y: float, reach: float) -> tuple[NDArray[np.float64], ...]:
        """The segments and fixed discs that a ray of ``reach`` from (x, y) may hit."""
        seg = self.segments
        if len(seg):
            length = np.hypot(seg[:, 2] - seg[:, 0], seg[:, 3] - seg[:, 1])
            gap = np.hypot(seg[:, 0] - x, seg[:, 1] - y) - length
            seg = seg[gap <= reach]
        discs = self.discs
        if len(discs):
            discs = discs[np.hypot(discs[:, 0] - x, discs[:, 1] - y) - discs[:, 2] <= reach]
        return seg, discs

    @staticmethod
    def cast(
        x: float | NDArray[np.float64],
        y: float | NDArray[np.float64],
        directions: NDArray[np.float64],
        segments: NDArray[np.float64],
        discs: NDArray[np.float64],
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Distance to the first hit along each direction (radians, CCW from east), inf for
        none, and the reflectivity of what was hit.

        ``x``, ``y``: the rays' origin, one for all or one per ray; ``discs``: (discs, 4) for
        all rays, or (rays, discs, 4), each ray its own (things that move while a batch of
        frames is cast)."""
        n = len(directions)
        ox = np.broadcast_to(np.asarray(x, dtype=float), (n,))[:, None]
        oy = np.broadcast_to(np.asarray(y, dtype=float), (n,))[:, None]
        dx, dy = np.cos(directions)[:, None], np.sin(directions)[:, None]
        best = np.full(n, np.inf)
        reflect = np.zeros(n)
        rays = np.arange(n)
        if len(segments):
            ax, ay = segments[:, 0] - ox, segments[:, 1] - oy
            ex, ey = segments[:, 2] - segments[:, 0], segments[:, 3] - segments[:, 1]
            denom = dx * ey - dy * ex
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (ax * ey - ay * ex) / denom
                u = (ax * dy - ay * dx) / denom
            t = np.where((np.abs(denom) > 1e-12) & (t > 0) & (u >= 0) & (u <= 1), t, np.inf)
            index = np.argmin(t, axis=1)
            hit = t[rays, index]
            closer = hit < best
            best = np.where(closer, hit, best)
            reflect = np.where(closer, segments[index, 4], reflect)
        if discs.shape[-2]:
            cx, cy = discs[..., 0] - ox, discs[..., 1] - oy
            b = dx * cx + dy * cy
            c = cx * cx + cy * cy - discs[..., 2] ** 2
            disc = b * b - c
            with np.errstate(invalid="ignore"):
                t = b - np.sqrt(disc)
            t = np.where((disc >= 0) & (t > 0), t, np.inf)
            index = np.argmin(t, axis=1)
            hit = t[rays, index]
            closer = hit < best
            best = np.where(closer, hit, best)
            hit_reflect = discs[index, 3] if discs.ndim == 2 else discs[rays, index, 3]
            reflect = np.where(closer, hit_reflect, reflect)
        return best, reflect


def world_polygons(
    frame: LocalFrame, area: AreaMap | None, obstacles: dict[str, Any] | None
) -> tuple[list[tuple[Polygon, float]], list[tuple[float, float, float, float]]]:
    """The map's keep-outs and the obstacles file's features in ``frame`` (the simulator's)."""
    polygons: list[tuple[Polygon, float]] = []
    discs: list[tuple[float, float, float, float]] = []
    if area is not None:
        for zone_id, keepout in area.keepouts.items():
            if zone_id.startswith(TEMPORARY_KEEPOUT_PREFIX):
                continue
            for polygon in _parts(keepout):
                ring = [
                    frame.to_local(*area.frame.to_geo(x, y)) for x, y in polygon.exterior.coords
                ]
                polygons.append((Polygon(ring), 0.6))
    for feature in (obstacles or {}).get("features", []):
        props = feature.get("properties") or {}
        if props.get("material") == "glass":
            continue  # clear glass: the beam passes
        reflectivity = float(props.get("reflectivity", 0.5))
        geometry = shape(feature["geometry"])
        if isinstance(geometry, Point):
            x, y = frame.to_local(geometry.y, geometry.x)
            discs.append((x, y, float(props.get("radius_m", 0.3)), reflectivity))
            continue
        for polygon in _parts(geometry):
            ring = [frame.to_local(lat, lon) for lon, lat, *_ in polygon.exterior.coords]
            polygons.append((Polygon(ring), reflectivity))
    return polygons, discs


def _parts(geometry: Any) -> list[Polygon]:
    if isinstance(geometry, Polygon):
        return [geometry]
    if isinstance(geometry, MultiPolygon):
        return list(geometry.geoms)
    return []


def load_obstacles(path: str) -> dict[str, Any] | None:
    """``sim.obstacles_file`` as GeoJSON (None when not set)."""
    if not path:
        return None
    data: dict[str, Any] = json.loads(Path(path).read_text(encoding="utf-8"))
    return data


class ScanGenerator:
    """Sans-IO: poses in, frames of the configured model out (noise seeded).

    :meth:`batch` makes many frames in one go, each from its own pose and time, as
    :meth:`frame` would one after the other: the same bytes for the same seed (the range noise
    and the dropouts draw from two streams, so how frames are grouped does not matter)."""

    def __init__(
        self,
        config: LidarSection,
        world: LidarWorld,
        *,
        lux: float = 0.0,
        rng: np.random.Generator | None = None,
    ) -> None:
        self.config = config
        self.model = MODELS[config.model]
        self.world = world
        self.lux = lux
        self.rng = rng or np.random.default_rng(1)
        self._drop_rng = np.random.default_rng(self.rng.integers(1 << 63))
        points_per_rev = self.model.points_per_s / self.model.rate_hz
        self.step_deg = 360.0 / points_per_rev
        self.speed_dps = round(360.0 * self.model.rate_hz)
        self.angle_deg = 0.0
        self.frames = 0
        light = min(1.0, lux / 100_000.0)
        self.reach_m = self.model.range_m * (1.0 - 0.4 * light)
        self._light = light
        self._cache: tuple[float, float, tuple[NDArray[np.float64], ...]] | None = None
        self._offsets = self.step_deg * np.arange(POINTS_PER_FRAME)

    def frame(self, pose: Pose, now: float, x: float, y: float) -> bytes:
        """The next frame, seen from the sensor on the vehicle at ``pose`` (``x``, ``y``: the
        vehicle in the world's frame), sent at ``now`` (seconds)."""
        return self.batch([now], [x], [y], [pose.yaw_rad])

    def next_starts(self) -> Iterator[int]:
        """The start angles (0.01 degree, as on the wire) of the frames to come."""
        angle = self.angle_deg
        turn = self.step_deg * POINTS_PER_FRAME
        while True:
            yield round(angle * 100) % 36000
            angle = (angle + turn) % 360.0

    def batch(
        self,
        times: Sequence[float],
        x: Sequence[float],
        y: Sequence[float],
        yaw: Sequence[float],
    ) -> bytes:
        """The next ``len(times)`` frames back to back (``FRAME_BYTES`` each), frame ``i`` sent
        at ``times[i]`` from the vehicle at ``x[i]``, ``y[i]`` (the world's frame) heading
        ``yaw[i]`` (radians, CCW from east)."""
        count = len(times)
        if not count:
            return b""
        config = self.config
        yaws = np.asarray(yaw, dtype=float)
        cos_yaw, sin_yaw = np.cos(yaws), np.sin(yaws)
        sx = np.asarray(x, dtype=float) + cos_yaw * config.mount_x_m - sin_yaw * config.mount_y_m
        sy = np.asarray(y, dtype=float) + sin_yaw * config.mount_x_m + cos_yaw * config.mount_y_m
        starts = np.empty(count)
        angle, turn = self.angle_deg, self.step_deg * POINTS_PER_FRAME
        for i in range(count):
            starts[i] = angle
            angle = (angle + turn) % 360.0
        self.angle_deg = angle
        angles = (starts[:, None] + self._offsets) % 360.0
        # The sensor's angles grow clockwise from its zero, which is turned yaw_deg from forward.
        directions = (yaws + math.radians(config.yaw_deg))[:, None] - np.radians(angles)
        stamps = np.asarray(times, dtype=float)
        people = self.world.pedestrians_over(stamps)
        ranges = np.empty((count, POINTS_PER_FRAME))
        reflect = np.empty((count, POINTS_PER_FRAME))
        for first, last, (segments, discs) in self._spans(sx, sy):
            span = slice(first, last)
            if people.shape[1]:
                moving = np.repeat(people[span], POINTS_PER_FRAME, axis=0)
                fixed = np.broadcast_to(discs, (len(moving), *discs.shape))
                discs = np.concatenate((fixed, moving), axis=1)
            hit, what = LidarWorld.cast(
                np.repeat(sx[span], POINTS_PER_FRAME),
                np.repeat(sy[span], POINTS_PER_FRAME),
                directions[span].ravel(),
                segments,
                discs,
            )
            ranges[span] = hit.reshape(-1, POINTS_PER_FRAME)
            reflect[span] = what.reshape(-1, POINTS_PER_FRAME)
        ranges = self._errors(ranges, reflect)
        intensities = np.clip(reflect * 255 * np.exp(-ranges / 30.0), 0, 255)
        intensities = np.where(ranges > 0, intensities, 0)
        self.frames += count
        # As round() and int() on each point (round half to even, truncation), for all the
        # frames at once: per-frame numpy and struct calls were most of a simulated drive.
        return encode_frames(
            self.speed_dps,
            angles[:, 0],
            angles[:, -1],
            np.rint(ranges * 1000.0),
            intensities,
            (stamps * 1000).astype(np.int64) % 30000,
        )

    def _spans(
        self, sx: NDArray[np.float64], sy: NDArray[np.float64]
    ) -> Iterator[tuple[int, int, tuple[NDArray[np.float64], ...]]]:
        """Runs of frames that share the world near the sensor (looked up again when the
        sensor has moved a metre from where it was last looked up)."""
        first = 0
        for i in range(len(sx)):
            cache = self._cache
            if cache is None or math.hypot(cache[0] - sx[i], cache[1] - sy[i]) > 1.0:
                if cache is not None and i > first:
                    yield first, i, cache[2]
                    first = i
                near = self.world.near(float(sx[i]), float(sy[i]), self.reach_m + 1.0)
                self._cache = (float(sx[i]), float(sy[i]), near)
        assert self._cache is not None
        yield first, len(sx), self._cache[2]

    def _errors(
        self, ranges: NDArray[np.float64], reflect: NDArray[np.float64]
    ) -> NDArray[np.float64]:
        finite = np.isfinite(ranges)
        safe = np.where(finite, ranges, 0.0)
        sigma = np.maximum(0.010, 0.015 * safe) / 2.0
        noisy = safe + self.rng.standard_normal(ranges.shape) * sigma
        # Dropouts: rare up close, more at the edge of the reach, with dark targets and light.
        edge = np.clip(safe / self.reach_m, 0.0, 1.0)
        p_drop = 0.002 + (0.05 + 0.3 * self._light) * edge**4 * (1.5 - reflect)
        lost = self._drop_rng.random(ranges.shape) < p_drop
        seen = finite & ~lost & (safe <= self.reach_m) & (safe >= self.model.min_range_m)
        return np.where(seen, np.round(np.maximum(noisy, 0.0) * 1000.0) / 1000.0, 0.0)


class LidarSimulator(Actor):
    """Writes the generator's frames to a pty as fast as the sensor sends them."""

    name = "sim:lidar"

    def __init__(
        self,
        bus: Bus,
        vehicle: VehicleModel,
        generator: ScanGenerator,
        *,
        origin: LocalFrame | None = None,
        world: Callable[[], LidarWorld | None] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        super().__init__(bus)
        self.vehicle = vehicle
        self.generator = generator
        self.origin = origin
        """The world's frame when it is not the vehicle's own (x, y from the vehicle's
        latitude and longitude); None: the vehicle's x, y."""
        self.world_source = world
        """Asked every tick for a changed world (the area map's); None: the world stays."""
        self._clock = clock
        self.line = PtyLine("simulated lidar")
        self.path = self.line.path

    async def run(self) -> None:
        try:
            await self._serve()
        except asyncio.CancelledError:
            self.close()
            raise

    async def _serve(self) -> None:
        period = self.generator.model.frame_period_s
        started = self._clock()
        sent = 0
        while True:
            await asyncio.sleep(TICK_S)
            if self.world_source is not None:
                world = self.world_source()
                if world is not None:
                    self.generator.world = world
            now = self._clock()
            due = int((now - started) / period) - sent
            if due > 0.5 / period:  # the loop stalled: skip, as a sensor's turn goes on
                sent += due - 1
                due = 1
            # The frames due are cast from the pose now, the time the reader will stamp them
            # with: a loop running late (10 ms or more) sends frames as fresh as their stamp.
            pose = self.vehicle.pose()
            x, y = self._position(pose)
            times = [started + (sent + i) * period for i in range(due)]
            self.line.write(self.generator.batch(times, [x] * due, [y] * due, [pose.yaw_rad] * due))
            sent += due

    def _position(self, pose: Pose) -> tuple[float, float]:
        if self.origin is None:
            return pose.x_m, pose.y_m
        return self.origin.to_local(pose.latitude, pose.longitude)

    def close(self) -> None:
        """Close the pty (idempotent)."""
        self.line.close()


class MapWorld:
    """The simulated world for the platform's current area map (rebuilt when it changes)."""

    def __init__(
        self,
        config: PlatformConfig,
        area: Callable[[], AreaMap | None],
    ) -> None:
        self.frame = LocalFrame(config.sim.latitude, config.sim.longitude)
        self._area = area
        self._obstacles = load_obstacles(config.sim.obstacles_file)
        self._pedestrians = config.sim.pedestrians
        self._seed = config.sim.seed
        self._built_for: object = None
        self._keepouts: set[str] = set()
        self.world = self._build(None)

    def __call__(self) -> LidarWorld | None:
        area = self._area()
        if area is self._built_for:
            return None
        keepouts = set(area.keepouts) if area is not None else set()
        keepouts = {k for k in keepouts if not k.startswith(TEMPORARY_KEEPOUT_PREFIX)}
        self._built_for = area
        if keepouts == self._keepouts:
            return None  # only the platform's own keep-outs changed (or none at all)
        self._keepouts = keepouts
        self.world = self._build(area)
        return self.world

    def _build(self, area: AreaMap | None) -> LidarWorld:
        polygons, discs = world_polygons(self.frame, area, self._obstacles)
        return LidarWorld(polygons, discs, self._pedestrians, random.Random(self._seed))


def generator_for(config: PlatformConfig, world: LidarWorld) -> ScanGenerator:
    return ScanGenerator(
        config.lidar, world, lux=config.sim.lux, rng=np.random.default_rng(config.sim.seed)
    )


def start_simulator(
    bus: Bus,
    supervisor: Supervisor,
    config: PlatformConfig,
    vehicle: VehicleModel,
    area: Callable[[], AreaMap | None],
) -> LidarSimulator | None:
    """In ``--sim``: the lidar on the simulated vehicle, unless ``lidar.port`` names another."""
    if config.lidar.port != LidarSection().port:
        _LOGGER.info("lidar.port is %s: no simulated lidar", config.lidar.port)
        return None
    world = MapWorld(config, area)
    simulator = LidarSimulator(
        bus, vehicle, generator_for(config, world.world), origin=world.frame, world=world
    )
    supervisor.start(simulator)
    return simulator


async def serve(config: PlatformConfig) -> None:
    """``brasidas-platform simulate lidar``: the pty path on stdout's first line, then serve a
    standing vehicle's view of ``sim.obstacles_file`` (and the demo map's shed)."""
    from brasidas.autonomy.areamap import parse_map
    from platformd.sim.demo_area import demo_map

    sim = config.sim
    area = parse_map(demo_map(sim.latitude, sim.longitude)) if sim.demo_map else None
    world = MapWorld(config, lambda: area)
    simulator = LidarSimulator(
        Bus(),
        vehicle_for(config),
        generator_for(config, world.world),
        origin=world.frame,
        world=world,
    )
    try:
        sys.stdout.write(simulator.path + "\n")
        sys.stdout.flush()
        await simulator.run()
    finally:
        simulator.close()
