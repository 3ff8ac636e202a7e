"""Localization from the lidar: odometry of every scan, fused with the GPS through its gate.

Runs when ``lidar.enabled`` and ``lidar.odometry``. Each ``LIDAR_SCAN`` is registered to the
local map (:mod:`brasidas.perception.odometry`) in this actor's own worker thread, the motion
prior being the last ``MOTOR_COMMAND`` (times the platform's top speed: the drive is open
loop) and the IMU's yaw change between scans (``ATTITUDE``: the Madgwick filter integrates
the gyro). ``GPS_FIX`` fixes go through the gate of :mod:`brasidas.perception.fusion` in the
same thread (one owner for the filter). The fusion starts at the first fix that moves fast
enough (0.5 m/s) to give a course: a heading the platform can trust without a compass.

The scans also build an occupancy grid (:mod:`brasidas.perception.grid`) at the fused pose
(not while dead reckoning), saved every ``GRID_SAVE_S`` and at stop to ``lidar.grid_file``
and loaded at start: its anchor becomes the local frame, so the robot's pose and the grid
it keeps stay in one frame across restarts (R-12).

Every ``MAP_EVERY`` scans the scan is also registered to the area map's keep-outs (buildings,
walls: :mod:`brasidas.perception.map_match`) from the fused pose, an absolute measurement that
makes the GPS's slow bias observable. That registration runs in a process of its own
(:mod:`platformd.map_match_process`: small_gicp holds the GIL for the whole of a call, and a
search or a town's walls take hundreds of milliseconds); its answer arrives with a later scan
and is carried forward by the motion since. Reloading the area map (R-5.3.2) only changes what the
scans are matched to: the fused pose carries on, so the robot stays localized; the new walls
are taken from the next scan.

Without GPS (indoors, under trees, a receiver disabled: ``gps_wait_s`` after the first scan
with no fix at all) the fusion starts in the map's own frame: at the robot's saved pose when a
grid was loaded (its anchor is the frame), else at the origin of a new map, facing east (its
anchor is the area map's origin, or 0, 0: a frame of its own, so the GPS fixes that come later
are not mixed into it). Every scan's step also goes into a pose graph
(:mod:`brasidas.perception.pose_graph`: keyframes a metre apart, loop closure by registering a
keyframe's scan to an earlier one's, iSAM2) in the same worker thread; the fused pose while GPS
or the area map's walls hold it is a prior on each keyframe. When a loop closes and neither
holds the pose, the graph's smoothed pose replaces the fused one (the drift since the place was
last seen taken out), and the grid is rebuilt from the keyframes at their smoothed poses in a
thread of its own, then swapped in. The keyframes are saved next to the grid
(``grid.keyframes.npz``) and loaded with it: a restarted robot closes loops against its old
map.

What it says: the ``perception`` telemetry's localization source and uncertainty, GPS fixes
accepted and refused, and why GPS is refused now (the annunciator's group 90 warning
``GPS_REJECTED``, which the MAVLink endpoint sends as STATUSTEXT).
"""

from __future__ import annotations

import asyncio
import bisect
import collections
import concurrent.futures
import contextlib
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import NDArray
from shapely.geometry import MultiPolygon

from brasidas import topics
from brasidas.actor import Actor
from brasidas.autonomy.areamap import AreaMap
from brasidas.autonomy.geo import LocalFrame, wrap
from brasidas.bus import Bus
from brasidas.clock import Clock, LoopClock, timeout_at
from brasidas.messages import Attitude, GpsFix, Velocity
from brasidas.perception.fusion import (
    FLOOR_NOISE,
    LIDAR_NOISE,
    PRIOR_NOISE,
    TURN_NOISE,
    FusedPose,
    GpsVerdict,
    PoseFusion,
)
from brasidas.perception.grid import GridError, OccupancyGrid
from brasidas.perception.map_match import MapMatch
from brasidas.perception.messages import LidarPose, PoseHold, RobotScan
from brasidas.perception.odometry import (
    LidarOdometry,
    OdometryStep,
    Pose2D,
    scan_points,
)
from brasidas.perception.pose_graph import (
    KeyframesError,
    PoseGraph,
    load_keyframes,
    save_keyframes,
)
from platformd.lidar_models import TEMPORARY_KEEPOUT_PREFIX
from platformd.map_match_process import MapMatchProcess, Pending
from platformd.map_relocalization import PLACED_SIGMAS, MapPlacer

_LOGGER = logging.getLogger(__name__)

HEADING_SPEED_MPS = 0.5
"""A fix moving at least this fast gives a course good enough to start from."""
FIX_EARLY_S = 0.02
"""A fix up to this much newer than the scan is taken with it (the filter carries the pose
forward to it along the scan's step)."""
FIX_HOLD_S = 0.3
"""Without scans, a fix waits this long for one before it is taken against the last pose."""
DRIVE_LAG_S = 0.25
"""The open-loop drive's response to a command (first order): the motion prior's speed and
turn follow the command with this lag, not at once (the robot accelerating from a stop to 5 m/s
covers a metre less than its command in its first second)."""
DRIVE_SPEED_DOUBT = 0.5
"""The prior's speed error, as a share of the gap between the command and the modelled speed
(a chassis's lag is not known exactly: load, slope, battery)."""
DOPPLER_FRESH_S = 0.5
"""An accepted fix's speed over ground (Doppler, ~0.05 m/s) newer than this resets the
modelled speed."""
NO_GYRO_YAW_SLACK_RAD = math.radians(15.0)
"""Without an IMU the prior does not know the turn: let the registration find it."""
GRID_SAVE_S = 30.0
IMU_STALE_S = 0.5
"""An IMU silent this long is taken as absent: the prior turns by the command."""
IMU_WAIT_S = 0.25
"""How long a scan waits for the IMU's sample of its time. On a loaded machine the IMU's
samples reach the localizer up to ~0.2 s after a scan of the same moment (half the scans
waited > 10 ms at load 7): read then, the turn in between went to the next scan, and the
registration, a few degrees off that prior, fell back to it (40 % of poses)."""
IMU_JUMP_RAD_S = math.radians(150.0)
"""A yaw change between scans faster than any rover turns: the IMU's filter was reset (it
starts again from yaw 0 after a reconnect or its gyro calibration), not a turn."""
MAP_EVERY = 5
"""Scans between matches to the area map (2 Hz for a 10 Hz lidar)."""
MAP_SEARCH_SIGMA_M = 0.5
"""Above this position uncertainty the match to the map searches around the estimate."""
MAP_ANSWER_LATE_S = 1.0
"""A map match answered later than this after its scan (a starved machine) is not fused: the
odometry that carries it forward to now has drifted as much as it would correct."""
MAP_DOUBT_AFTER = 3
"""Fits to the map refused in a row after which the fusion's certainty is doubted."""
GPS_WAIT_S = 30.0
"""With a GPS receiver configured: scans for this long without a single fix (indoors, under
trees) and the robot localizes in its map's own frame."""
SAVED_POSE_SIGMAS = (0.3, math.radians(5.0))
"""Starting at the saved pose: the robot may have been pushed a little while off (the first
keyframes close loops against the loaded ones and pin it)."""
REBUILD_SHIFT_M = 0.1
"""A loop closure that moved no keyframe by a grid cell leaves the grid as it is (going round
a known place closes a loop at every keyframe)."""
REBUILD_EVERY_S = 10.0
"""At most one grid rebuild this often (200 keyframes take ~0.3 s of CPU to rebuild)."""
OWN_FRAME_HOLD = (
    "no GPS, and no saved map tied to it: the route's latitudes and longitudes cannot be "
    "placed in the robot's own map frame (hand driving only)"
)
"""The patrol's hold in a map frame of the robot's own."""
GRAPH_START_SIGMAS = (0.01, 0.01, 0.001)
"""The first node of a graph begun with the fusion: the frame is where it starts."""


class Localizer(Actor):
    """Scans, commands, attitude and fixes in; the fused pose and the GPS gate's verdicts out."""

    name = "localization"

    def __init__(
        self,
        bus: Bus,
        max_speed_mps: float,
        *,
        grid_path: Path | None = None,
        clock: Clock | None = None,
        area: Callable[[], AreaMap | None] | None = None,
        max_yaw_rate_rad_s: float = 0.0,
        gps_sigma_m: float = 2.1,
        gps_wait_s: float | None = None,
        loop_closure: bool = True,
    ) -> None:
        """``gps_wait_s``: scans without a fix after which the robot localizes in its map's
        own frame (0: at once, no GPS; None: never, it waits for GPS)."""
        super().__init__(bus)
        self.gps_wait = gps_wait_s
        self.loop_closure = loop_closure
        self.graph: PoseGraph | None = None
        """The keyframes and their loop closures (worker thread; None before the fusion
        starts, or with ``loop_closure`` off)."""
        self.loop_corrections: list[float] = []
        """How far each loop closure moved the fused pose (m), the latest 100."""
        self._loaded_keyframes: list[tuple[Pose2D, NDArray[np.float32]]] = []
        self._grid_base: OccupancyGrid | None = None
        """A loaded grid without keyframes (an older file): rebuilds start from it."""
        self._rebuilder = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="grid")
        self._rebuild: tuple[concurrent.futures.Future[OccupancyGrid], int] | None = None
        """The grid being rebuilt after a loop closure, and the keyframes it was given."""
        self._rebuild_due = False
        """A closure moved the keyframes since the last rebuild began."""
        self._rebuild_at: float | None = None
        self.grid_rebuilds = 0
        self.rebuild_cpu_s = 0.0
        """The last grid rebuild's thread CPU time."""
        self.map_frame = False
        """Started without GPS, in the map's own frame."""
        self.geo_anchored = False
        """The local frame's anchor is a GPS position (a fix, or a grid saved under GPS)."""
        self.placer: MapPlacer | None = None
        """(Worker thread.) The loaded grid searched for the robot when there is no GPS."""
        self.hold = ""
        """(Worker thread.) Why the pose must not be driven on now ("" when it may)."""
        self._hold_published: str | None = None
        self._fix_seen = False
        self._first_scan_at: float | None = None
        self.gps_sigma = gps_sigma_m
        """The receiver's absolute error at HDOP 1 (``autonomy.gps_sigma_m``)."""
        self.max_yaw_rate = max_yaw_rate_rad_s
        """The turn rate of a full ``angular`` command: without an IMU, the prior's turn."""
        self._turn = 0.0
        self._command = (0.0, 0.0)
        """The last MOTOR_COMMAND: linear m/s, angular rad/s."""
        self.drive = (0.0, 0.0)
        """(Worker thread.) The modelled speed (m/s) and turn (rad/s) the drive has reached."""
        self._drive_at: float | None = None
        self._area = area or (lambda: None)
        self._area_seen: object = None
        self.maps = MapMatchProcess()
        """The area map's walls and the matches to them, in a process of their own."""
        self.has_walls = False
        self.walls_set = 0
        """How many times the walls were set (a map loaded or reloaded)."""
        self.map_answers = 0
        """Matches answered (fits and refusals) against the current walls."""
        self.map_refusals = 0
        self._rings: list[NDArray[np.float64]] = []
        self._map_disagreements = 0
        self._map_doubted = False
        self.map_refusal = ""
        """Why the last scan did not fit the area map ("" when it did, or no map)."""
        self.measured_at: float | None = None
        """When the pose last rested on a measurement: a registered scan or an accepted fix."""
        self.grid_path = grid_path
        self.grid: OccupancyGrid | None = None
        self.grid_error = ""
        """Why the saved grid was not loaded ("" when it was, or there was none)."""
        self._grid_saved_at: float | None = None
        self._grid_dirty = False
        self.max_speed = max_speed_mps
        self.clock: Clock = clock or LoopClock()
        self.odometry = LidarOdometry()
        self.fusion = PoseFusion(gps_sigma_m=gps_sigma_m)
        self.frame: LocalFrame | None = None
        self.last: OdometryStep | None = None
        self.fused: FusedPose | None = None
        self.gps_refusal = ""
        """Why GPS is refused now ("" when trusted, or no fix yet)."""
        self._speed = 0.0
        self._imu: collections.deque[tuple[float, float, float]] = collections.deque(maxlen=256)
        """The IMU's recent yaws: (stamp, raw yaw, continuous yaw: unwrapped, resets taken
        out), to read its yaw at each scan's time."""
        """The IMU's latest yaw (rad) and its time."""
        self._yaw_at_scan: float | None = None
        """The IMU's yaw at the last scan it was known for."""
        self._turn_without_imu = 0.0
        """The turn the scans since then were given without it (the command's, or found)."""
        self.imu_jumps = 0
        self.scans_done = 0
        """Scans processed, with the fixes due with them, and published."""
        self._scan: RobotScan | None = None
        self._fixes: collections.deque[GpsFix] = collections.deque(maxlen=8)
        self._wake = asyncio.Event()
        self._imu_arrived = asyncio.Event()
        self.imu_waits = 0
        """Scans that waited for the IMU to reach their time."""
        self._worker = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="localize")

    async def run(self) -> None:
        self.subscribe(topics.LIDAR_SCAN, self._on_scan)
        self.subscribe(topics.MOTOR_COMMAND, self._on_command)
        self.subscribe(topics.ATTITUDE, self._on_attitude)
        self.subscribe(topics.GPS_FIX, self._on_fix)
        loop = asyncio.get_running_loop()
        await loop.run_in_executor(self._worker, self.load_grid)
        try:
            while True:
                await self._wake.wait()
                self._wake.clear()
                if self._scan is not None:
                    await self._imu_caught_up(self._scan.time)
                scan, self._scan = self._scan, None
                fixes = self._due_fixes(scan)
                yaw_rate = self._yaw_rate(scan)
                area = self._area()
                if area is not self._area_seen and self.frame is not None:
                    self._area_seen = area
                    await loop.run_in_executor(self._worker, self.set_area, area)
                accepted = await loop.run_in_executor(
                    self._worker, self.process, scan, fixes, self._speed, yaw_rate, self._turn
                )
                self._publish(accepted)
                self.scans_done = self.odometry.scans
        finally:
            try:
                await loop.run_in_executor(self._worker, self.save_grid)
            finally:
                self._worker.shutdown(wait=False, cancel_futures=True)
                self._rebuilder.shutdown(wait=False, cancel_futures=True)
                self.maps.close()

    def _publish(self, accepted: list[GpsFix]) -> None:
        for fix in accepted:
            self.bus.publish(topics.GPS_ACCEPTED, fix)
        if self.hold != self._hold_published:
            self._hold_published = self.hold
            self.bus.publish(topics.POSE_HOLD, PoseHold(self.hold))
        fused, frame = self.fused, self.frame
        if fused is None or frame is None:
            return
        latitude, longitude = frame.to_geo(fused.x_m, fused.y_m)
        self.bus.publish(
            topics.LIDAR_POSE,
            LidarPose(
                fused.time,
                latitude,
                longitude,
                fused.yaw_rad,
                fused.sigma_m,
                fused.sigma_yaw_rad,
                fused.source,
                self.measured_at,
            ),
        )

    def _due_fixes(self, scan: RobotScan | None) -> list[GpsFix]:
        """The fixes the filter can take now: those taken up to the scan it is about to
        process. A newer fix waits for its scan: on a loaded machine the scans are processed
        late, and a fix compared with a pose half a second old is "off" by half a second of
        driving (2.5 m at 5 m/s), refused as a jump, and the pose left to the prior. Without
        scans for :data:`FIX_HOLD_S` (the lidar stalled) they are taken as they are."""
        horizon = scan.time + FIX_EARLY_S if scan is not None else self.clock.time() - FIX_HOLD_S
        due: list[GpsFix] = []
        while self._fixes and self._fixes[0].stamp <= horizon:
            due.append(self._fixes.popleft())
        return due

    def _on_scan(self, scan: RobotScan) -> None:
        self._scan = scan
        self._wake.set()

    def _on_fix(self, fix: GpsFix) -> None:
        self._fix_seen = True
        self._fixes.append(fix)
        self._wake.set()

    def _on_command(self, velocity: Velocity) -> None:
        self._speed = velocity.linear * self.max_speed
        self._turn = velocity.angular * self.max_yaw_rate

    def _on_attitude(self, attitude: Attitude) -> None:
        raw, stamp = math.radians(attitude.yaw_deg), attitude.stamp
        if not self._imu:
            self._imu.append((stamp, raw, raw))
            self._imu_arrived.set()
            return
        last_stamp, last_raw, continuous = self._imu[-1]
        if stamp <= last_stamp:
            return
        turn = wrap(raw - last_raw)
        if abs(turn) / (stamp - last_stamp) > IMU_JUMP_RAD_S:
            self.imu_jumps += 1
            _LOGGER.info(
                "IMU yaw jumped %.0f° (its filter restarted): not taken as a turn",
                math.degrees(turn),
            )
            turn = 0.0
            if len(self._imu) >= 2:  # the turn goes on at the rate it had
                before_stamp, _raw, before = self._imu[-2]
                turn = (continuous - before) / (last_stamp - before_stamp) * (stamp - last_stamp)
        self._imu.append((stamp, raw, continuous + turn))
        self._imu_arrived.set()

    async def _imu_caught_up(self, when: float) -> None:
        """Until the IMU has a sample at or after ``when`` (a scan's time), at most
        :data:`IMU_WAIT_S`; at once without an IMU or with one gone quiet."""
        samples = self._imu
        if not samples or samples[-1][0] >= when or when - samples[-1][0] > IMU_STALE_S:
            return
        self.imu_waits += 1
        with contextlib.suppress(TimeoutError):
            async with timeout_at(self.clock, self.clock.time() + IMU_WAIT_S):
                while samples[-1][0] < when:
                    self._imu_arrived.clear()
                    await self._imu_arrived.wait()

    def _imu_yaw_at(self, when: float) -> float | None:
        """The IMU's continuous yaw at ``when``, between the samples around it; None when its
        latest sample is older than :data:`IMU_STALE_S` (no IMU, or it stopped)."""
        samples = self._imu
        if not samples or when - samples[-1][0] > IMU_STALE_S:
            return None
        if when >= samples[-1][0]:
            return samples[-1][2]
        if when <= samples[0][0]:
            return samples[0][2]
        stamps = [sample[0] for sample in samples]
        i = bisect.bisect_right(stamps, when)
        (t0, _r0, y0), (t1, _r1, y1) = samples[i - 1], samples[i]
        return y0 + (y1 - y0) * (when - t0) / (t1 - t0)

    def _yaw_rate(self, scan: RobotScan | None) -> float | None:
        """The IMU's mean yaw rate between the previous scan's time and this one's (None: no
        IMU). Read at the scans' own times, not when they are processed: on a loaded machine
        they are processed late and in bursts, and the turn would go to the wrong scan."""
        if scan is None:
            return None
        yaw = self._imu_yaw_at(scan.time)
        if yaw is None:  # kept: the IMU's turn meanwhile is taken when it is back
            return None
        previous, self._yaw_at_scan = self._yaw_at_scan, yaw
        last = self.last
        if previous is None or last is None or scan.time <= last.time:
            return 0.0
        # Across scans it was stale for (a starved reader), the IMU's turn is what the prior's
        # (the command's) was not: taken as none, a turn on the spot was missed by 95°.
        turn = yaw - previous - self._turn_without_imu
        self._turn_without_imu = 0.0
        return turn / (scan.time - last.time)

    # ------------------------------------------------------------------ worker thread

    def process(
        self,
        scan: RobotScan | None,
        fixes: list[GpsFix],
        speed_mps: float,
        yaw_rate: float | None,
        commanded_turn: float = 0.0,
    ) -> list[GpsFix]:
        """(Worker thread.) The scan through the odometry, then the fixes through the gate
        (compared with where the step put the robot at each fix's time); the fixes the gate
        did not refuse. ``speed_mps`` and ``commanded_turn`` are the command: the prior
        follows them with the drive's lag (:data:`DRIVE_LAG_S`), its speed reset by the
        fixes' Doppler. Without the IMU's ``yaw_rate`` the turn is the commanded one: taken
        as none, a robot that turned would keep its old heading wherever the scans do not
        register (an open field), the fused pose would drive off the way it no longer faces,
        and honest fixes, even RTK ones, be refused as a jump."""
        points: NDArray[np.float64] = np.empty((0, 2))
        if scan is not None:
            speed, turn, doubt = self._drive_to(scan.time, speed_mps, commanded_turn)
            self.odometry.yaw_slack_rad = None if yaw_rate is not None else NO_GYRO_YAW_SLACK_RAD
            rate = yaw_rate if yaw_rate is not None else turn
            points = scan_points(scan, speed, rate)
            step = self.odometry.update(points, scan.time, speed, rate)
            if yaw_rate is None:
                self._turn_without_imu += step.delta.yaw_rad
            if step.source != "lidar" and (self.last is None or self.last.source == "lidar"):
                _LOGGER.info("lidar odometry on the motion prior: %s", step.reason)
            self.last = step
            prior_doubt = doubt if step.source != "lidar" else 0.0
            self.fusion.predict(step.delta, step.source, scan.time, prior_doubt)
            self._maybe_start_without_gps(scan.time, points)
            self._check_placed(scan.time, points)
            if step.source == "lidar" and self.fusion.started:
                self.measured_at = scan.time
            self._collect_map_match()
            if self.fusion.started and self.odometry.scans % MAP_EVERY == 0:
                self._match_map(points)
        accepted = [fix for fix in fixes if self._gps(fix)]
        if scan is not None and self.fusion.started and self.loop_closure:
            self._keyframe(self.last, points)
        self.fused = self.fusion.pose() if self.fusion.started else None
        if scan is not None and self.fused is not None and self.fused.source != "prior":
            self._map(scan.time, points)
        return accepted

    def _maybe_start_without_gps(self, now: float, points: NDArray[np.float64]) -> None:
        """(Worker thread.) No fix at all for ``gps_wait_s`` of scans: start in the map's own
        frame, where the scan is placed in a loaded grid (:mod:`platformd.map_relocalization`:
        not before it is placed with confidence), or at the origin of a new map."""
        if self._first_scan_at is None:
            self._first_scan_at = now
        if self.fusion.started or self.gps_wait is None:
            return
        if self._fix_seen and self.geo_anchored:
            return  # GPS is here (a map of the robot's own frame waits for no fix)
        if now - self._first_scan_at < self.gps_wait:
            return
        saved = self.grid.pose if self.grid is not None else None
        if self.frame is None:
            area = self._area()
            anchor = (area.frame.latitude, area.frame.longitude) if area is not None else (0, 0)
            self.frame = LocalFrame(*anchor)
        placer = self.placer
        if placer is not None:
            placed = placer.search(points, now, saved, self.odometry.pose)
            self.hold = placer.hold
            if placed is None:
                return
            self.fusion.start_at(placed, *PLACED_SIGMAS, now)
        elif saved is not None:
            self.fusion.start_at(saved, *SAVED_POSE_SIGMAS, now)
        else:
            self.fusion.start_at(Pose2D(0.0, 0.0, 0.0), 0.0, 0.0, now)
        self.map_frame = True
        if not self.geo_anchored:
            self.hold = OWN_FRAME_HOLD
        _LOGGER.info(
            "localization: no GPS: in the map's own frame, %s",
            "placed in the saved map"
            if placer is not None
            else f"from the saved pose ({saved.x_m:.1f}, {saved.y_m:.1f}) m"
            if saved is not None
            else "a new map from here",
        )

    def _check_placed(self, now: float, points: NDArray[np.float64]) -> None:
        """(Worker thread.) Once placed in the saved map without GPS: the scan still fits it,
        else the robot holds and the map is searched again; a new place moves the pose."""
        placer = self.placer
        if placer is None or not self.map_frame or not self.fusion.started:
            return
        if placer.placed:
            here = Pose2D(*(float(v) for v in self.fusion.state))
            match, lost = placer.track(points, here)
            if lost:
                self.hold = placer.hold
            elif match is not None:
                pose, covariance = match
                if self.fusion.map_fix(pose.x_m, pose.y_m, pose.yaw_rad, covariance, now):
                    self.measured_at = now
                    self._map_disagreements = 0
                else:  # a filter sure of a wrong heading (a turn on the prior) would lock it out
                    self._disagreed()
            return
        placed = placer.search(points, now, None, self.odometry.pose)
        self.hold = placer.hold
        if placed is not None:
            # The graph's path since it was lost is the drifted one: a loop it closed would
            # take the pose back there. A new graph from here, on the saved map's keyframes.
            if self.graph is not None:
                self._loaded_keyframes = self.graph.keyframes()[: self.graph.first_live]
                self.graph = None
            self.fusion.moved_to(placed)
            self.fusion.cov = np.diag(
                (PLACED_SIGMAS[0] ** 2, PLACED_SIGMAS[0] ** 2, PLACED_SIGMAS[1] ** 2)
            )

    def _keyframe(self, step: OdometryStep | None, points: NDArray[np.float64]) -> None:
        """(Worker thread.) The scan's step into the pose graph; a loop it closes corrects the
        fused pose (unless GPS or the map's walls hold it) and has the grid rebuilt."""
        self._swap_rebuilt_grid()
        if self._rebuild_due:
            self._start_rebuild()
        if step is None:
            return
        fused = self.fusion.pose()
        here = Pose2D(fused.x_m, fused.y_m, fused.yaw_rad)
        if self.graph is None:
            loaded = self._loaded_keyframes if self.geo_anchored or self.map_frame else []
            self._loaded_keyframes = []
            self.graph = PoseGraph(here, GRAPH_START_SIGMAS, loaded=loaded)
            return
        graph = self.graph
        delta = step.delta
        distance = math.hypot(delta.x_m, delta.y_m)
        along, across, turn = LIDAR_NOISE if step.source == "lidar" else PRIOR_NOISE
        sigmas = (
            along * distance + FLOOR_NOISE[0],
            across * distance + FLOOR_NOISE[1],
            turn * distance + TURN_NOISE * abs(delta.yaw_rad) + FLOOR_NOISE[2],
        )
        keyframes = len(graph.poses)
        closure = graph.odometry(delta, sigmas, points)
        held = fused.source in ("gps+lidar", "map+lidar")
        if len(graph.poses) > keyframes and held:
            sigma = max(fused.sigma_m, 0.05)
            graph.prior(here, (sigma, sigma, max(fused.sigma_yaw_rad, math.radians(1.0))))
        if closure is None:
            return
        if not held:
            corrected = graph.pose
            self.loop_corrections.append(math.dist((here.x_m, here.y_m), _xy(corrected)))
            del self.loop_corrections[:-100]
            self.fusion.moved_to(corrected)
            _LOGGER.info(
                "localization: loop closed (keyframe %d on %d): pose moved %.2f m",
                closure.k,
                closure.j,
                self.loop_corrections[-1],
            )
        if closure.moved_m >= REBUILD_SHIFT_M:
            self._rebuild_due = True
            self._start_rebuild()

    def _start_rebuild(self) -> None:
        """(Worker thread.) Rebuild the grid from the keyframes at their smoothed poses, in
        the grid's own thread (a town's keyframes take a second or more)."""
        graph, frame = self.graph, self.frame
        if graph is None or frame is None:
            return
        now = self.fusion.time
        if self._rebuild is not None or (
            self._rebuild_at is not None and now - self._rebuild_at < REBUILD_EVERY_S
        ):
            return  # after the one under way, or in a while
        self._rebuild_due = False
        self._rebuild_at = now
        keyframes = graph.keyframes()
        base = self._grid_base or OccupancyGrid(frame.latitude, frame.longitude)
        base.geo = self.geo_anchored
        future = self._rebuilder.submit(self._rebuilt, base, keyframes)
        self._rebuild = (future, len(graph.poses))

    def _rebuilt(
        self, base: OccupancyGrid, keyframes: list[tuple[Pose2D, NDArray[np.float32]]]
    ) -> OccupancyGrid:
        """(Grid thread.)"""
        started = time.thread_time()
        grid = base.rebuilt(keyframes)
        self.rebuild_cpu_s = time.thread_time() - started
        return grid

    def _swap_rebuilt_grid(self) -> None:
        """(Worker thread.) A finished rebuild becomes the grid: the keyframes added since it
        started are integrated on top."""
        if self._rebuild is None or not self._rebuild[0].done():
            return
        (future, counted), self._rebuild = self._rebuild, None
        try:
            grid = future.result()
        except GridError as err:
            self.grid_error = str(err)
            return
        graph = self.graph
        if graph is not None:
            for pose, points in graph.keyframes()[counted:]:
                grid.integrate(pose, np.asarray(points, dtype=float))
        grid.scans = max(grid.scans, (self.grid.scans if self.grid else 0)) + 1
        self.grid = grid
        self.grid_rebuilds += 1
        self._grid_dirty = True

    def _drive_to(
        self, now: float, speed_mps: float, turn_rad_s: float
    ) -> tuple[float, float, float]:
        """The modelled drive carried to ``now`` towards the command: the speed and turn it
        reached (mean over the interval) and how wrong that speed may be (m/s)."""
        speed, turn = self.drive
        dt = 0.0 if self._drive_at is None else max(0.0, now - self._drive_at)
        self._drive_at = now
        blend = 1.0 - math.exp(-dt / DRIVE_LAG_S)
        new_speed = speed + (speed_mps - speed) * blend
        new_turn = turn + (turn_rad_s - turn) * blend
        self.drive = (new_speed, new_turn)
        doubt = DRIVE_SPEED_DOUBT * abs(speed_mps - (speed + new_speed) / 2)
        return (speed + new_speed) / 2, (turn + new_turn) / 2, doubt

    def set_area(self, area: AreaMap | None) -> None:
        """(Worker thread.) Match the scans to ``area``'s keep-outs from now on."""
        frame = self.frame
        assert frame is not None
        rings: list[NDArray[np.float64]] = []
        # In a map frame of its own (no GPS ever) the area map's latitudes and longitudes are
        # nowhere in particular: its walls would pull the pose to a wrong place.
        if area is not None and self.geo_anchored:
            for zone_id, keepout in area.keepouts.items():
                if zone_id.startswith(TEMPORARY_KEEPOUT_PREFIX):
                    continue  # the lidar's own obstacles, not the map's walls
                parts = keepout.geoms if isinstance(keepout, MultiPolygon) else (keepout,)
                for polygon in parts:
                    coords = polygon.exterior.coords
                    rings.append(
                        np.array([frame.to_local(*area.frame.to_geo(x, y)) for x, y in coords])
                    )
        if _same_rings(rings, self._rings):
            return  # only the lidar's own keep-outs changed: the walls stay, and the match
        self.set_walls(rings)
        _LOGGER.info(
            "localization: %s",
            f"matching scans to the outlines of the area map's keep-outs ({len(rings)})"
            if rings
            else "no walls in the area map to match scans to",
        )

    def set_walls(self, rings: list[NDArray[np.float64]]) -> None:
        """(Worker thread.) Match the scans to these outlines (the local frame's metres)."""
        self._rings = rings
        self.has_walls = bool(rings)
        self.maps.set_walls(rings)
        self.walls_set += 1
        self.map_answers = 0
        self.map_refusal = ""

    def _match_map(self, points: NDArray[np.float64]) -> None:
        """Ask the matching process where this scan fits the walls (the answer comes with a
        later scan: :meth:`_collect_map_match`)."""
        if not self.has_walls:
            return
        fusion = self.fusion
        guess = Pose2D(*(float(v) for v in fusion.state))
        uncertain = fusion.pose().sigma_m > MAP_SEARCH_SIGMA_M or self._map_doubted
        self.maps.submit(points, guess, fusion.time, uncertain)

    def _collect_map_match(self) -> None:
        done = self.maps.collect()
        if done is None:
            return
        pending, match = done
        self.map_answers += 1
        if self.fusion.time - pending.time > MAP_ANSWER_LATE_S:
            match = f"the map's answer came {self.fusion.time - pending.time:.1f} s late"
        if isinstance(match, str):
            self.map_refusals += 1
            self.map_refusal = match
            if "from the estimate" in match:  # a fit, but too far from the estimate
                self._disagreed()
            return
        self._fuse_map_match(pending, match)

    def _fuse_map_match(self, pending: Pending, match: MapMatch) -> None:
        """The fit of a scan a few scans ago, carried forward by the odometry's motion since
        (the fused pose then, ``pending.start``, to the fused pose now)."""
        now_pose = Pose2D(*(float(v) for v in self.fusion.state))
        pose = match.pose.compose(pending.start.between(now_pose))
        now = self.fusion.time
        if self.fusion.map_fix(pose.x_m, pose.y_m, pose.yaw_rad, match.covariance, now):
            self.map_refusal = ""
            self.measured_at = now
            self._map_disagreements = 0
            self._map_doubted = False
        else:
            self.map_refusal = "the map's fit disagrees with the estimate"
            self._disagreed()

    def _disagreed(self) -> None:
        """The map fits, but not where the fusion is sure the robot is: after a few in a row
        the fusion is doubted (widened) and the map searched around it, so a filter sure of a
        wrong heading (an IMU reset taken for a turn, a bad start) does not lock the map out."""
        self._map_disagreements += 1
        if self._map_disagreements >= MAP_DOUBT_AFTER:
            self._map_disagreements = 0
            self._map_doubted = True
            self.fusion.doubt(1.0, math.radians(10.0))
            _LOGGER.info("localization: the map disagreed %d times: searching", MAP_DOUBT_AFTER)

    def _map(self, now: float, points: NDArray[np.float64]) -> None:
        fused, frame = self.fused, self.frame
        if fused is None or frame is None:
            return
        if self.grid is None:
            self.grid = OccupancyGrid(frame.latitude, frame.longitude)
            self.grid.geo = self.geo_anchored
        try:
            self.grid.integrate(Pose2D(fused.x_m, fused.y_m, fused.yaw_rad), points)
        except GridError as err:
            if not self.grid_error:
                _LOGGER.warning("occupancy grid not updated: %s", err)
            self.grid_error = str(err)
            return
        self._grid_dirty = True
        if self._grid_saved_at is None:
            self._grid_saved_at = now
        elif now - self._grid_saved_at >= GRID_SAVE_S:
            self._grid_saved_at = now
            self.save_grid()

    def load_grid(self) -> None:
        """(Worker thread.) The saved grid, if any: its anchor becomes the local frame."""
        path = self.grid_path
        if path is None or not path.exists():
            return
        try:
            grid = OccupancyGrid.load(path)
        except GridError as err:
            self.grid_error = str(err)
            _LOGGER.warning("occupancy grid refused, starting a new one: %s", err)
            return
        self.grid = grid
        self.frame = LocalFrame(grid.latitude, grid.longitude)
        self.geo_anchored = grid.geo
        self.placer = MapPlacer(grid) if self.gps_wait is not None else None
        try:
            if not keyframes_path(path).exists():  # a grid saved without (an older file)
                raise FileNotFoundError(keyframes_path(path))
            self._loaded_keyframes = load_keyframes(keyframes_path(path))
        except FileNotFoundError:
            self._grid_base = grid
        except KeyframesError as err:
            _LOGGER.warning("keyframes refused (loops close on the new ones only): %s", err)
            self._grid_base = grid
        rows, cols = grid.log_odds.shape
        _LOGGER.info(
            "occupancy grid loaded from %s: %d scans, %.0f x %.0f m",
            path,
            grid.scans,
            cols * grid.resolution,
            rows * grid.resolution,
        )

    def save_grid(self) -> None:
        """(Worker thread.) Write the grid if it changed since it was last written."""
        if self.grid is None or self.grid_path is None or not self._grid_dirty:
            return
        fused = self.fused
        if fused is not None:
            self.grid.pose = Pose2D(fused.x_m, fused.y_m, fused.yaw_rad)
        try:
            self.grid.save(self.grid_path)
            if self.graph is not None:
                save_keyframes(keyframes_path(self.grid_path), self.graph.keyframes())
        except OSError as err:
            _LOGGER.warning("occupancy grid not saved to %s: %s", self.grid_path, err)
            return
        self._grid_dirty = False

    def fix_sigma(self, fix: GpsFix) -> float:
        """A fix's error per axis: the receiver's, ``gps_sigma_m`` times its HDOP."""
        return self.gps_sigma * max(1.0, fix.hdop or 1.0)

    def _gps(self, fix: GpsFix) -> bool:
        """The fix through the gate: False when refused (before the fusion starts there is
        nothing to check it against, and it passes)."""
        if self.frame is None:
            self.frame = LocalFrame(fix.latitude, fix.longitude)
            self.geo_anchored = True
        if not self.geo_anchored:
            return False  # a map frame of its own: a fix is not a position in it
        if not self.fusion.started:
            speed, course = fix.speed_mps, fix.course_deg
            if speed is None or course is None or speed < HEADING_SPEED_MPS:
                return True  # no heading yet: the fusion waits for the robot to move
            self.fusion.heading_rad = math.radians(90.0 - course)
        x, y = self.frame.to_local(fix.latitude, fix.longitude)
        relocalized = self.fusion.relocalized
        verdict: GpsVerdict = self.fusion.gps(x, y, fix.stamp, self.fix_sigma(fix))
        if self.fusion.relocalized != relocalized:
            _LOGGER.warning(
                "re-localized to the GPS: the pose had dead-reckoned %.1f m off it",
                verdict.innovation_m,
            )
        if verdict.accepted:
            self.measured_at = fix.stamp
            if fix.speed_mps is not None and self.fusion.time - fix.stamp <= DOPPLER_FRESH_S:
                # Over ground, unsigned: the drive's sign (a robot reversing reports its speed)
                sign = (
                    -1.0 if self.drive[0] < 0 or (self.drive[0] == 0 and self._speed < 0) else 1.0
                )
                self.drive = (sign * fix.speed_mps, self.drive[1])
        refusal = "" if verdict.accepted else verdict.reason
        if bool(refusal) != bool(self.gps_refusal):
            if refusal:
                _LOGGER.warning("GPS refused, not followed: %s", refusal)
            else:
                _LOGGER.info("GPS agrees with the odometry again: fixes accepted")
        self.gps_refusal = refusal
        return verdict.accepted

    def map_place(self) -> str:
        """Without GPS, where the robot stands in its map: placed in the saved map (and how
        well), or why its pose is not driven on; "" with GPS."""
        if self.hold:
            return self.hold
        placer = self.placer
        return placer.status if placer is not None and self.map_frame else ""

    def counters(self) -> dict[str, int]:
        return {
            "scans": self.odometry.scans,
            "fallbacks": self.odometry.fallbacks,
            "partial": self.odometry.partial,
            "gps_accepted": self.fusion.accepted,
            "gps_rejected": self.fusion.rejected,
            "map_matches": self.fusion.map_accepted,
            "map_refused": self.fusion.map_refused + self.map_refusals,
            "keyframes": len(self.graph.poses) if self.graph is not None else 0,
            "loop_closures": self.graph.closures if self.graph is not None else 0,
            "grid_rebuilds": self.grid_rebuilds,
            "relocalized": self.fusion.relocalized,
            "map_searches": self.placer.searches if self.placer is not None else 0,
            "map_placements": self.placer.placements if self.placer is not None else 0,
            "map_lost": self.placer.losses if self.placer is not None else 0,
        }


def keyframes_path(grid_path: Path) -> Path:
    """The pose graph's keyframes, saved next to the grid."""
    return grid_path.with_name(grid_path.stem + ".keyframes.npz")


def _xy(pose: Pose2D) -> tuple[float, float]:
    return (pose.x_m, pose.y_m)


def _same_rings(a: list[NDArray[np.float64]], b: list[NDArray[np.float64]]) -> bool:
    return len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
