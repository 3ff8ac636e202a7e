"""The browser console's side of the station: pushes, video, and the console's drive feed.

A page opens the local API's WebSocket (``/api/rpc/ws``, the same JSON-RPC the CLI uses) and
calls ``console_subscribe``: from then on the station pushes JSON-RPC notifications on that
socket — ``platforms`` (the beacons heard), ``connections`` (sessions, override, who drives),
``telemetry`` (one platform's report, as each snapshot arrives) and ``notification`` (group 90
warnings raised and cleared) — and, after ``video_watch``, the NavCam's access units as binary
messages (:mod:`stationd.video_feed`). Nothing is polled by the page.

The console's drive feed (``console_drive``) is for the page that engaged the override through
``console_override``: each call sets the velocity for ``console.drive_timeout`` (0.2 s) only,
so a page that stops sending — a closed or hidden tab, a stalled socket, a crashed script —
stops the robot here, whatever its JavaScript did; a closed socket stops it at once.

The hub is split along the page's own seams: :mod:`~stationd.console.session` (a page's
socket, its pushes' limits, the shared base), :mod:`~stationd.console.media` (NavCam and
microphone feeds, why a feed is silent, the page's latency for the speed cap, push-to-talk),
:mod:`~stationd.console.drive` (override and the drive watchdog) and
:mod:`~stationd.console.hub` (the actor: sessions, pushes, kept notifications).
"""

from stationd.console.hub import ConsoleHub, async_setup

__all__ = ["ConsoleHub", "async_setup"]
