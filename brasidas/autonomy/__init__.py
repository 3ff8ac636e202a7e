"""Autonomy's pure parts (sans-IO): the area map, routes, localization, planning, following.

Nothing here touches the bus, a clock or a file descriptor except :mod:`.route`'s store;
the platform's actors (``platformd.autonomy``) feed these with messages and the time.
"""
