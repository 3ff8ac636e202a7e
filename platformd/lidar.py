"""The lidar subsystem (issue 30): the reader and obstacle analysis live in
:mod:`platformd.lidar_reader`, loaded only when ``lidar.enabled``, so a platform without a lidar
loads neither NumPy nor Shapely at start."""

from __future__ import annotations

from platformd.context import PlatformContext


async def async_setup(ctx: PlatformContext) -> None:
    if not ctx.config.lidar.enabled:
        return
    from platformd import lidar_reader

    await lidar_reader.async_setup(ctx)
