"""The lidar subsystem (issue 30): the reader and obstacle analysis live in
:mod:`platformd.lidar_reader`, loaded only when ``lidar.enabled``, so a platform without a lidar
loads neither NumPy nor Shapely at start."""

from __future__ import annotations

from brasidas.config import PlatformConfig
from platformd.context import PlatformContext


def preload(config: PlatformConfig) -> None:
    """The reader, with NumPy and Shapely, and the views it starts, when ``lidar.enabled``."""
    if not config.lidar.enabled:
        return
    import platformd.lidar_reader
    import platformd.perception_view

    if config.lidar.map_obstacles:
        import platformd.obstacle_zones  # noqa: F401


async def async_setup(ctx: PlatformContext) -> None:
    if not ctx.config.lidar.enabled:
        return
    from platformd import lidar_reader

    await lidar_reader.async_setup(ctx)
