"""The lidars' data-sheet figures and the names shared by the reader, the simulator and the
patrol's keep-outs: without Shapely or NumPy, so a platform without a lidar loads neither."""

from __future__ import annotations

from dataclasses import dataclass

from brasidas.codecs.ldlidar import POINTS_PER_FRAME
from brasidas.config.lidar import LidarSection
from brasidas.perception.messages import SEEN_KEEPOUT_PREFIX

TEMPORARY_KEEPOUT_PREFIX = SEEN_KEEPOUT_PREFIX
"""Keep-outs the platform made from what it saw: not part of the simulated world."""


@dataclass(frozen=True)
class LidarModel:
    """A sensor's figures from its data sheet."""

    name: str
    baudrate: int
    points_per_s: int
    range_m: float
    min_range_m: float = 0.02
    rate_hz: float = 10.0

    @property
    def frame_period_s(self) -> float:
        return POINTS_PER_FRAME / self.points_per_s


MODELS = {
    "ld19": LidarModel("LD19", 230400, 4500, 12.0),
    "ld06": LidarModel("LD06", 230400, 4500, 12.0),
    "stl27l": LidarModel("STL-27L", 921600, 21600, 25.0, min_range_m=0.03),
}


def baudrate_of(config: LidarSection) -> int:
    """The configured baud rate, or the model's own for 0."""
    return config.baudrate or MODELS[config.model].baudrate
