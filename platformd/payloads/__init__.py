"""Payloads (issue 13): each enabled in ``payload.enabled`` registers its command groups
(100-110) with the command router, with their specs (name, payload format, engagement), and
itself (:class:`~platformd.context.PayloadInfo`: its groups and its streams) on
``ctx.payloads``, which ``connect``'s capabilities list as ``payloads``."""

from __future__ import annotations

from typing import Any

from brasidas.config import PlatformConfig
from platformd.context import PlatformContext


def preload(config: PlatformConfig) -> None:
    """Each enabled payload's module."""
    if "turret" in config.payload.enabled:
        import platformd.payloads.turret  # noqa: F401


async def async_setup(ctx: PlatformContext) -> None:
    ctx.capabilities.register("payloads", lambda: describe(ctx))
    if "turret" in ctx.config.payload.enabled:
        from platformd.payloads import turret

        await turret.async_setup(ctx)


def describe(ctx: PlatformContext) -> list[dict[str, Any]]:
    """Each payload carried: its name, command groups and streams (connect's ``payloads``)."""
    return [
        {"name": info.name, "groups": list(info.groups), "streams": list(info.streams)}
        for info in ctx.payloads.values()
    ]
