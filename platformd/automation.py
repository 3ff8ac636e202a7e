"""Onboard automations that an operator can switch off live (R-3), and their states.

Each automation's owner handles its own system command and reports its switch here; the
``AUTOMATIONS`` topic holds them all (telemetry's ``automation`` section):

=====  ==================  =========================================  ====================
code   name                what it switches                           owner
=====  ==================  =========================================  ====================
10.8   ``patrol``          the autonomous patrol                      platformd.autonomy
10.9   ``auto_framerate``  NavCam 5 fps idle / 30 fps under override  platformd.media
10.10  ``stream_retries``  rebuilding failed streams with backoff     platformd.media
20.0   ``diagnostics``     the diagnostics report                     platformd.telemetry
20.4   ``battery_monitor`` the battery level                          platformd.motor
=====  ==================  =========================================  ====================
"""

from __future__ import annotations

from brasidas import topics
from brasidas.bus import Bus
from brasidas.messages import Automations


def report_switch(bus: Bus, name: str, on: bool) -> None:
    """Publish that automation ``name`` is now on or off (no message when unchanged).
    Must run on the event loop."""
    last = bus.last(topics.AUTOMATIONS)
    switches = dict(last.switches) if last is not None else {}
    if switches.get(name) is on:
        return
    switches[name] = on
    bus.publish(topics.AUTOMATIONS, Automations(tuple(sorted(switches.items()))))
