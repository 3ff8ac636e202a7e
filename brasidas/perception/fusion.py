"""Fusion of lidar odometry and GPS, with a gate that rejects a GPS that disagrees (pure).

An extended Kalman filter over the pose in the plane (x east, y north, yaw counter-clockwise
from east; metres and radians in the GPS's local frame). Each odometry step moves it, with
noise growing with the distance and the turn (more when the step was the open-loop prior);
each GPS fix that passes the gate corrects it. GTSAM was the issue's choice of estimator, but
its 4.3 wheel requires pytest >= 9 at run time, which conflicts with the test tools pinned
here; this filter is the honest stand-in until it does not.

A GPS fix is never followed when it disagrees with the odometry-propagated pose:

- **jump**: its innovation against the filter's prediction fails a chi-square test (two
  degrees of freedom, ``gate_chi2``): a sudden offset of tens of metres is rejected at the
  first bad fix;
- **drag**: over the last ``drag_window_s`` the GPS moved more than ``drag_m`` (plus
  ``drag_fraction`` of the distance travelled) differently from the odometry: a receiver pulled
  off slowly (spoofed at walking pace) is caught before the innovation gate would see it. The
  NEO-6M's own error wanders over minutes (a few decimetres in ten seconds), so its honest
  drift stays well under the threshold;
- after either, fixes are refused until ``clear_fixes`` in a row pass both tests again.

A "jump" no larger than the dead reckoning since the last accepted fix could have drifted
(:data:`DEAD_RECKONING_DRIFT` of the distance driven on the motion prior, the scans not
registering) is the odometry's error, not the GPS's: after ``clear_fixes`` such fixes in a
row the pose is re-localized to the GPS. Refused as a jump instead, every later fix was
refused too (each as far off), the pose dead-reckoned on for good and the patrol held, on a
starved machine, "inside" a building it was metres from.

Each fix is weighted by the receiver's accuracy: ``gps_sigma_m`` (the configured absolute
error at HDOP 1, ``autonomy.gps_sigma_m``: 2.1 m for a NEO-6M, 0.02 m for RTK) times the
fix's HDOP, plus how far the robot moves in the time between the fix and the filter's last
step. Its absolute error, not its fix-to-fix jitter: the error wanders over minutes, so the
walls of the area map, when they fit, must win over it. Weighted by a fixed, NEO-6M-sized
sigma instead, an RTK fix barely moved a dead-reckoned pose, which drifted a metre sideways
of the truth in an open field (nothing for the scans to register).
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from brasidas.autonomy.geo import wrap
from brasidas.perception.odometry import Pose2D

LIDAR_NOISE = (0.02, 0.01, 0.003)
"""Odometry from registration: sigma along and across per metre, and of yaw per metre (rad)."""
PRIOR_NOISE = (0.10, 0.05, 0.02)
"""Odometry from the commanded speed and gyro (open loop: wheel slip, load)."""
TURN_NOISE = 0.02
"""Sigma of yaw per radian turned."""
FLOOR_NOISE = (0.002, 0.002, 0.0005)
"""Per step, even standing still."""
JUMP_FLOOR_M = 1.0
"""A fix this close to the estimate is never a jump: against an RTK fix's centimetres the
odometry's own error (a scan registered to a single post) would fail the chi-square test, and
an honest fix refused is one the pose no longer follows. A spoofer pulling by less than this
at a time is a drag, which the drag test catches."""
DEAD_RECKONING_DRIFT = 2.0
"""How far the pose may have drifted per metre driven on the motion prior: as far as the
heading reversed (open loop, on a starved machine a turn on the spot was missed by 95° and
the pose ran 5 m off in 3.6 m of driving). Only a fix further than the robot can have got is
a jump the prior can tell: with scans that do not register, little else can be."""
MAX_AHEAD_S = 0.2
"""A fix newer than the last odometry step is compared with the estimate carried at most this
far ahead along that step (the scans stalled: beyond it, it is compared with the last step)."""
DRAG_PRIOR_SHARE = 0.2
"""Above this share of the drag window's distance on the motion prior, no drag is judged."""


@dataclass(frozen=True)
class GpsVerdict:
    accepted: bool
    reason: str
    """Why it was refused ("" when accepted)."""
    innovation_m: float
    """How far the fix was from the predicted position."""


@dataclass(frozen=True)
class FusedPose:
    time: float
    x_m: float
    y_m: float
    yaw_rad: float
    sigma_m: float
    """Position uncertainty: the square root of the larger eigenvalue of its covariance."""
    source: str
    """What it rests on: "map+lidar" (the scans fit the area map's walls lately), "gps+lidar",
    "lidar" (neither lately), "prior" (odometry from the commanded speed only), or "none" (not
    started: no fix yet)."""
    sigma_yaw_rad: float = 0.0


class PoseFusion:
    """Odometry steps and GPS fixes in (each with ``now``); the fused pose out."""

    def __init__(
        self,
        *,
        gps_sigma_m: float = 3.0,
        gate_chi2: float = 13.8,
        drag_window_s: float = 10.0,
        drag_m: float = 3.0,
        drag_fraction: float = 0.05,
        clear_fixes: int = 5,
        gps_fresh_s: float = 3.0,
    ) -> None:
        self.gps_sigma = gps_sigma_m
        self.gate_chi2 = gate_chi2
        self.drag_window = drag_window_s
        self.drag_m = drag_m
        self.drag_fraction = drag_fraction
        self.clear_fixes = clear_fixes
        self.gps_fresh = gps_fresh_s
        self.state: NDArray[np.float64] = np.zeros(3)
        self.cov: NDArray[np.float64] = np.eye(3)
        self.started = False
        self.heading_rad: float | None = None
        """Yaw to start from with the first fix (None: east, with a wide sigma)."""
        self.time = 0.0
        self.odometer = np.zeros(2)
        """Where the odometry alone has carried the robot (world frame): the drag test's
        reference, untouched by GPS corrections."""
        self.travelled_m = 0.0
        self.dead_reckoned_m = 0.0
        """Of it, on the motion prior (the scans did not register): not evidence of a drag."""
        self._history: collections.deque[tuple[float, float, float, float, float, float, float]] = (
            collections.deque()
        )
        """(time, gps x, gps y, odometer x, odometer y, travelled, dead reckoned) of recent
        fixes."""
        self.suspect = ""
        """"jump" or "drag": GPS is refused until it agrees again ("" when trusted)."""
        self._agreeing = 0
        self.last_gps_at: float | None = None
        self.last_source = "none"
        self.accepted = 0
        self.rejected = 0
        self.map_gate_chi2 = 16.3
        """Three degrees of freedom at 0.999."""
        self.last_map_at: float | None = None
        self.map_accepted = 0
        self.map_refused = 0
        self.last_rejection = ""
        self._step: tuple[float, float, NDArray[np.float64]] = (0.0, 0.0, np.zeros(2))
        """The last odometry step: its end time, length (s) and motion (world frame)."""
        self._step_at: float | None = None
        self._reckoned_at_fix = 0.0
        """:attr:`dead_reckoned_m` at the last accepted fix."""
        self._drifted = 0
        """Fixes in a row off by no more than the dead reckoning could have drifted."""
        self.relocalized = 0
        """Times the pose was re-localized to the GPS after dead reckoning off it."""

    # ------------------------------------------------------------------ odometry

    def predict(self, delta: Pose2D, source: str, now: float, speed_sigma_mps: float = 0.0) -> None:
        """The robot moved ``delta`` (its own frame at the previous step). ``speed_sigma_mps``:
        how wrong the speed it was reckoned on may be (an open-loop drive's lag behind its
        command), on top of the per-metre noise."""
        dt = 0.0 if self._step_at is None else max(0.0, now - self._step_at)
        self._step_at = now
        self.time = now
        self.last_source = source
        yaw = float(self.state[2])
        c, s = math.cos(yaw), math.sin(yaw)
        dx, dy = delta.x_m, delta.y_m
        world = np.array((c * dx - s * dy, s * dx + c * dy))
        self._step = (now, dt, world)
        self.odometer += world
        distance = math.hypot(dx, dy)
        self.travelled_m += distance
        if source != "lidar":
            self.dead_reckoned_m += distance
        if not self.started:
            return
        self.state[:2] += world
        self.state[2] = wrap(yaw + delta.yaw_rad)
        f = np.array(((1.0, 0.0, -world[1]), (0.0, 1.0, world[0]), (0.0, 0.0, 1.0)))
        g = np.array(((c, -s, 0.0), (s, c, 0.0), (0.0, 0.0, 1.0)))
        along, across, turn = LIDAR_NOISE if source == "lidar" else PRIOR_NOISE
        sigmas = np.array(
            (
                along * distance + FLOOR_NOISE[0] + speed_sigma_mps * dt,
                across * distance + FLOOR_NOISE[1],
                turn * distance + TURN_NOISE * abs(delta.yaw_rad) + FLOOR_NOISE[2],
            )
        )
        self.cov = f @ self.cov @ f.T + g @ np.diag(sigmas**2) @ g.T

    # ------------------------------------------------------------------ GPS

    def gps(self, x_m: float, y_m: float, now: float, sigma_m: float | None = None) -> GpsVerdict:
        """A fix in the local frame: accepted (and fused) or refused, with the reason.
        ``sigma_m``: its error per axis (None: ``gps_sigma_m``)."""
        sigma = self.gps_sigma if sigma_m is None else sigma_m
        if not self.started:
            self.time = now
            self._start(x_m, y_m, sigma)
            self._remember(now, x_m, y_m)
            return self._accept(now, 0.0)
        innovation = np.array((x_m, y_m)) - self.position_at(now)
        self.time = max(self.time, now)
        s = self.cov[:2, :2] + np.eye(2) * sigma**2
        d2 = float(innovation @ np.linalg.solve(s, innovation))
        distance = float(np.hypot(*innovation))
        reason = ""
        drifted = False
        if d2 > self.gate_chi2 and distance > JUMP_FLOOR_M:
            reckoned = self.dead_reckoned_m - self._reckoned_at_fix
            drifted = distance <= JUMP_FLOOR_M + DEAD_RECKONING_DRIFT * reckoned
            if not drifted:
                reason = f"jump: {distance:.1f} m from where the odometry puts the robot"
        drag = self._drag(now, x_m, y_m)
        self._remember(now, x_m, y_m)
        if drag and not reason:
            reason = drag
        if reason:
            self._drifted = 0
            return self._reject(reason, distance)
        if drifted:
            self._drifted += 1
            if self._drifted < self.clear_fixes:
                waiting = (
                    f"dead-reckoned {distance:.1f} m off the GPS: "
                    f"{self._drifted} of {self.clear_fixes} agree"
                )
                return self._reject(waiting, distance, probation=True)
            # The odometry's drift, now known: the fix pulls the pose all the way.
            self.cov[:2, :2] += np.eye(2) * distance**2
            s = self.cov[:2, :2] + np.eye(2) * sigma**2
            self.suspect = ""
            self.relocalized += 1
        self._drifted = 0
        if self.suspect:
            self._agreeing += 1
            if self._agreeing < self.clear_fixes:
                waiting = f"{self.suspect} suspected: {self._agreeing} of {self.clear_fixes} agree"
                return self._reject(waiting, distance, probation=True)
            self.suspect = ""
        k = self.cov[:, :2] @ np.linalg.inv(s)
        self.state = self.state + k @ innovation
        self.state[2] = wrap(float(self.state[2]))
        self.cov = (np.eye(3) - k[:, :2] @ np.eye(2, 3)) @ self.cov
        return self._accept(now, distance)

    def position_at(self, when: float) -> NDArray[np.float64]:
        """The estimate's position moved to ``when`` along the last odometry step: a fix
        taken inside that step is compared with where the robot was then, not where the step
        ended (at 5 m/s a scan period is half a metre: added on top of a fix that already
        holds it, the step ran the estimate ahead of the robot)."""
        step_end, dt, world = self._step
        if dt <= 0.0:
            return self.state[:2].copy()
        shift = max(-dt, min(MAX_AHEAD_S, when - step_end))
        return self.state[:2] + world * (shift / dt)

    def start_at(self, pose: Pose2D, sigma_m: float, sigma_yaw_rad: float, now: float) -> None:
        """Start without GPS: at ``pose`` in the map's own frame (the robot's saved pose, or
        the origin of a new map)."""
        self.state = np.array((pose.x_m, pose.y_m, pose.yaw_rad))
        self.cov = np.diag((sigma_m**2, sigma_m**2, sigma_yaw_rad**2))
        self.time = now
        self.started = True

    def moved_to(self, pose: Pose2D) -> None:
        """The pose graph closed a loop: its smoothed pose replaces the estimate (the
        covariance stays: the closure fixes the path's shape, not the frame's anchor)."""
        self.state = np.array((pose.x_m, pose.y_m, pose.yaw_rad))

    def _start(self, x_m: float, y_m: float, sigma_m: float) -> None:
        yaw = self.heading_rad if self.heading_rad is not None else 0.0
        yaw_sigma = math.radians(10.0) if self.heading_rad is not None else math.pi
        self.state = np.array((x_m, y_m, yaw))
        self.cov = np.diag((sigma_m**2, sigma_m**2, yaw_sigma**2))
        self.started = True

    def _drag(self, now: float, x_m: float, y_m: float) -> str:
        history = self._history
        while history and history[0][0] < now - self.drag_window:
            history.popleft()
        if not history or now - history[0][0] < 0.7 * self.drag_window:
            return ""
        t0, gx, gy, ox, oy, travelled, reckoned = history[0]
        moved = self.travelled_m - travelled
        if moved > 0 and (self.dead_reckoned_m - reckoned) > DRAG_PRIOR_SHARE * moved:
            return ""  # the odometry was mostly the commanded speed: it cannot judge the GPS
        gps_moved = np.array((x_m - gx, y_m - gy))
        odometry_moved = self.odometer - (ox, oy)
        apart = float(np.hypot(*(gps_moved - odometry_moved)))
        limit = self.drag_m + self.drag_fraction * (self.travelled_m - travelled)
        if apart <= limit:
            return ""
        return f"drag: GPS moved {apart:.1f} m unlike the odometry in {now - t0:.0f} s"

    def _remember(self, now: float, x_m: float, y_m: float) -> None:
        ox, oy = self.odometer
        self._history.append(
            (now, x_m, y_m, float(ox), float(oy), self.travelled_m, self.dead_reckoned_m)
        )

    def _accept(self, now: float, distance: float) -> GpsVerdict:
        self.accepted += 1
        self._reckoned_at_fix = self.dead_reckoned_m
        self.last_gps_at = now
        return GpsVerdict(True, "", distance)

    def _reject(self, reason: str, distance: float, *, probation: bool = False) -> GpsVerdict:
        self.rejected += 1
        if not probation:
            self.suspect = reason.split(":")[0]  # "jump" or "drag"
            self._agreeing = 0
        self.last_rejection = reason
        return GpsVerdict(False, reason, distance)

    # ------------------------------------------------------------------ the map

    def map_fix(
        self, x_m: float, y_m: float, yaw_rad: float, covariance: NDArray[np.float64], now: float
    ) -> bool:
        """Where a scan fits the area map's walls (an absolute pose, ``covariance`` 3x3):
        fused unless it fails the chi-square gate against the prediction (a wrong match)."""
        if not self.started:
            return False
        self.time = now
        innovation = np.array((x_m, y_m, yaw_rad)) - self.state
        innovation[2] = wrap(float(innovation[2]))
        s = self.cov + covariance
        d2 = float(innovation @ np.linalg.solve(s, innovation))
        if d2 > self.map_gate_chi2:
            self.map_refused += 1
            return False
        k = self.cov @ np.linalg.inv(s)
        self.state = self.state + k @ innovation
        self.state[2] = wrap(float(self.state[2]))
        self.cov = (np.eye(3) - k) @ self.cov
        self.cov = (self.cov + self.cov.T) / 2
        self.last_map_at = now
        self.map_accepted += 1
        return True

    def doubt(self, sigma_m: float, sigma_yaw_rad: float) -> None:
        """Widen the pose's uncertainty to at least these: the map refused in a row means the
        filter is sure of a wrong pose (it locks out what would correct it)."""
        self.cov[:2, :2] += np.eye(2) * sigma_m**2
        self.cov[2, 2] += sigma_yaw_rad**2

    # ------------------------------------------------------------------ the estimate

    def pose(self) -> FusedPose:
        x, y, yaw = (float(v) for v in self.state)
        sigma = math.sqrt(max(0.0, float(np.linalg.eigvalsh(self.cov[:2, :2])[-1])))
        if not self.started:
            source = "none"
        elif self.last_source != "lidar":
            source = "prior"
        elif self.last_map_at is not None and self.time - self.last_map_at <= self.gps_fresh:
            source = "map+lidar"
        elif self.last_gps_at is not None and self.time - self.last_gps_at <= self.gps_fresh:
            source = "gps+lidar"
        else:
            source = "lidar"
        sigma_yaw = math.sqrt(max(0.0, float(self.cov[2, 2])))
        return FusedPose(self.time, x, y, yaw, sigma, source, sigma_yaw)
