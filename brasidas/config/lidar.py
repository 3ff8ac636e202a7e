"""The ``[lidar]`` section: a 2-D time-of-flight lidar (LDROBOT LD06/LD19, STL-27L), issue 30."""

from __future__ import annotations

from dataclasses import dataclass

from brasidas.config.loader import Check, above, at_least, each, non_empty, one_of, setting

LIDAR_MODELS = ("ld19", "ld06", "stl27l")
LIDAR_BAUD_RATES = (0, 230400, 921600)


def _sector(value: str) -> bool:
    start, sep, end = value.partition(":")
    try:
        return bool(sep) and all(-360.0 <= float(v) <= 360.0 for v in (start, end))
    except ValueError:
        return False


def parse_sector(value: str) -> tuple[float, float]:
    """``"FROM:TO"`` (degrees) as a pair; the config check has already accepted it."""
    start, _, end = value.partition(":")
    return float(start), float(end)


@dataclass(frozen=True)
class LidarSection:
    enabled: bool = False
    """Read a 2-D lidar and stop for what it sees (collision prevention in every mode). In
    --sim the simulated vehicle then carries one (on a pty), seeing the world of ``sim.*``."""
    model: str = setting("ld19", one_of(*LIDAR_MODELS))
    """"ld19" or "ld06" (12 m, 4,500 points/s, 230400 baud), "stl27l" (25 m, 21,600 points/s,
    921600 baud)."""
    port: str = setting("/dev/ttyUSB2", non_empty)
    """Its serial device (the sensor's UART through a USB adapter, or a Pi UART)."""
    baudrate: int = setting(0, one_of(*LIDAR_BAUD_RATES))
    """0: the model's own (230400 for the LD06/LD19, 921600 for the STL-27L)."""
    mount_x_m: float = setting(0.25, at_least(-5, most=5))
    """Where the sensor sits: metres forward of the robot's centre (negative: behind it)."""
    mount_y_m: float = setting(0.0, at_least(-5, most=5))
    """Metres left of the robot's centre (negative: right)."""
    height_m: float = setting(0.35, at_least(0, most=3))
    """Height of the scan plane above the ground: nothing lower than this is seen."""
    yaw_deg: float = setting(0.0, at_least(-180, most=180))
    """The sensor's zero angle relative to the robot's forward axis, counter-clockwise."""
    masked_sectors: tuple[str, ...] = setting((), each(Check("FROM:TO degrees", _sector)))
    """Bearings hidden by the robot's own body (mast, payload), "FROM:TO" in degrees clockwise
    from the robot's forward axis, e.g. "170:190" for a mast behind the sensor."""
    body_radius_m: float = setting(0.1, at_least(0, most=5))
    """Returns closer than this to the sensor are the robot itself and are ignored (the
    sensor's housing, a cable); less than ``clearance_m``, or an obstacle the robot stopped
    for would vanish into it. Larger parts of the robot: ``masked_sectors``."""
    half_width_m: float = setting(0.35, above(0, most=5))
    """Half the robot's width: the corridor ahead (or behind) that must be clear."""
    clearance_m: float = setting(0.4, at_least(0, most=10))
    """Distance kept from an obstacle after stopping, measured from the sensor (mount it at
    the front), along the robot's axis."""
    min_points: int = setting(3, at_least(1, most=50))
    """Neighbouring returns that make an obstacle: fewer is noise (a single stray return)."""
    reaction_s: float = setting(0.5, at_least(0, most=5))
    """Dead time from an obstacle entering the scan to the wheels slowing: up to a revolution
    (0.1 s), the analysis, the motor controller's refresh (0.1 s) and the drive's own lag
    (~0.25 s on the simulated rover)."""
    odometry: bool = True
    """Lidar odometry (small_gicp) fused with the GPS, whose fixes are refused when they jump or
    drag away from it (spoofing: reported, never followed); about 1.5 ms of CPU a scan."""
    grid_file: str = ""
    """The occupancy grid the odometry builds, kept across restarts (R-12). Empty:
    $XDG_STATE_HOME/brasidas/grid.npz."""
    grid_period_s: float = setting(5.0, at_least(0.2, most=60))
    """How often the grid, while it grows, is drawn again for the stations, the console's map
    and the recording (an image of the whole grid, made in a thread)."""
    map_obstacles: bool = True
    """Obstacles seen become temporary keep-outs of the patrol's map, which re-plans around
    them (false: the robot only stops for them)."""
    scan_timeout_s: float = setting(0.5, above(0, most=10))
    """No scan for this long: the lidar is lost, and the robot stops until it returns."""
