"""The forward speed limit a command gets from the lidar's :class:`Proximity` limits: straight
ahead's, or along the arc the command turns. Pure and numpy-free: the motion arbiter imports it
at start-up, before any lidar or map is there."""

from __future__ import annotations

from brasidas.perception.messages import Proximity


def forward_for(limits: Proximity, linear: float, angular: float) -> tuple[float, str]:
    """The forward limit and its reason for a command: straight ahead's, or along its arc
    (the lower of the two arcs around its turn ratio, or of straight and the first)."""
    if linear <= 0 or not limits.turns:
        return limits.forward_limit, limits.reason if limits.forward_limit < 1.0 else ""
    ratio = angular / linear
    side = [t for t in limits.turns if (t[0] > 0) == (ratio > 0)]
    side.sort(key=lambda t: abs(t[0]))
    candidates = [(0.0, limits.forward_limit, limits.reason), *side]
    magnitude = abs(ratio)
    below = max((t for t in candidates if abs(t[0]) <= magnitude), key=lambda t: abs(t[0]))
    above = [t for t in candidates if abs(t[0]) >= magnitude]
    chosen = [below, *(above[:1] if above else [])]
    worst = min(chosen, key=lambda t: t[1])
    return worst[1], worst[2]


def limit_for(limits: Proximity, linear: float, angular: float) -> tuple[float, str]:
    """What the motion arbiter lets a command do forward, and why: the limit along its arc,
    and along the tighter arc it drives once slowed to that (the same turn rate, slower)."""
    forward, why = forward_for(limits, linear, angular)
    if linear <= forward:
        return forward, why
    tighter, tighter_why = forward_for(limits, forward, angular)
    return (tighter, tighter_why) if tighter < forward else (forward, why)
