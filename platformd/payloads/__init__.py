"""Payloads (issue 13): each enabled in ``payload.enabled`` registers its command groups
(100-110) with the command router, with their specs (name, payload format, engagement)."""

from __future__ import annotations

from platformd.context import PlatformContext


async def async_setup(ctx: PlatformContext) -> None:
    if "turret" in ctx.config.payload.enabled:
        from platformd.payloads import turret

        await turret.async_setup(ctx)
