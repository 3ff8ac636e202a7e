"""The planner process: holds the visibility graph of the patrol's map and answers plans.

NumPy and Shapely hold the GIL in long blocks while a graph is built; in a thread of the
platform's process that stalls its event loop (tens of milliseconds). Here the build and the
plans run in a process of their own (``python -m brasidas.autonomy.planner_worker FD``),
started, restarted and killed by the patrol (:mod:`platformd.autonomy.planner_client`).

The two talk over a Unix socket in frames (:func:`frame`): a JSON header and a body of bytes.

- ``{"op": "map", "revision", "clearance"}`` with the map's GeoJSON as the body: the graph of
  that map (a few keep-outs changed since the last one: the last graph changed, not rebuilt).
  A newer map stops the build of an older one (answered ``dropped``).
- ``{"op": "edit", "revision", "base", "clearance"}`` with ``{"add": [features], "remove":
  [ids]}`` as the body: keep-outs changed on map ``base`` (the last one sent); answered
  ``resend`` when this process does not have that one (it was started since).
- ``{"op": "plan", "revision", "id", "start", "goal"}``: a path on that revision's graph,
  queued behind its build; ``stale`` when the graph is of another revision.

Answers: ``ready`` (revision, build_s, nodes, edges, incremental), ``dropped``, ``resend``, ``failed``
(error), ``path`` (points), ``unreachable`` (reason), ``stale``. The process exits when the
socket closes (the platform is gone): it never outlives its owner.
"""

from __future__ import annotations

import contextlib
import os
import queue
import signal
import socket
import struct
import sys
import threading
import time
from typing import Any

import orjson

HEADER = struct.Struct("!II")
"""A frame's header: the JSON header's length, the body's length."""
MAX_FRAME_BYTES = 64 * 1024 * 1024
"""A frame larger than this is a broken peer (a map is at most a few MB)."""
PR_SET_PDEATHSIG = 1
"""prctl(2): the signal a process gets when its parent dies."""
NICENESS = 5
"""Below the platform: on a busy CPU its event loop (the robot's control) runs first, a build
waits (nice 5 is about a third of the CPU of a process at 0 when both want it)."""
MAP_OPS = ("map", "edit")
INCREMENTAL_MOST = 20
"""Keep-outs changed at once up to which the last graph is changed rather than rebuilt."""


def frame(header: dict[str, Any], body: bytes = b"") -> bytes:
    """One frame: lengths, the JSON header, the body."""
    encoded = orjson.dumps(header)
    return HEADER.pack(len(encoded), len(body)) + encoded + body


def parse_header(data: bytes) -> tuple[int, int]:
    """The header's and the body's lengths, or ValueError when they are out of bounds."""
    head, body = HEADER.unpack(data)
    if head + body > MAX_FRAME_BYTES:
        raise ValueError(f"a frame of {head + body} bytes (at most {MAX_FRAME_BYTES})")
    return head, body


class _Worker:
    """The graph of the latest map and its plans (the process's main thread)."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.inbox: queue.Queue[tuple[dict[str, Any], bytes]] = queue.Queue()
        self.lock = threading.Lock()
        self.newest_map = -1
        """The newest map revision received (the reader thread's view)."""
        self.building: tuple[int, threading.Event] | None = None
        self.revision = -1
        self.received: tuple[int, Any] | None = None
        """The last map received (revision, AreaMap): what the next edit changes."""
        self.area: Any = None
        self.planner: Any = None

    # ------------------------------------------------------------------ reader thread

    def read(self) -> None:
        """(Reader thread.) Frames into the inbox; a newer map stops the build under way;
        the socket's end (the platform is gone) ends the process."""
        try:
            while True:
                head, size = parse_header(self._exactly(HEADER.size))
                header = orjson.loads(self._exactly(head))
                body = self._exactly(size)
                if header.get("op") in MAP_OPS:
                    with self.lock:
                        self.newest_map = max(self.newest_map, int(header["revision"]))
                        if self.building is not None and self.building[0] < self.newest_map:
                            self.building[1].set()
                self.inbox.put((header, body))
        except (OSError, ValueError, EOFError):
            pass
        os._exit(0)

    def _exactly(self, count: int) -> bytes:
        chunks, left = [], count
        while left:
            chunk = self.sock.recv(min(left, 1 << 20))
            if not chunk:
                raise EOFError("the platform closed the planner's socket")
            chunks.append(chunk)
            left -= len(chunk)
        return b"".join(chunks)

    # ------------------------------------------------------------------ main thread

    def serve(self) -> None:
        while True:
            header, body = self.inbox.get()
            try:
                if header.get("op") in MAP_OPS:
                    self._map(header, body)
                elif header.get("op") == "plan":
                    self._plan(header)
            except Exception as exc:  # a bug here must not leave the patrol holding forever
                self._send({"op": "failed", "revision": header.get("revision"), "error": repr(exc)})

    def _send(self, header: dict[str, Any]) -> None:
        self.sock.sendall(frame(header))

    def _map(self, header: dict[str, Any], body: bytes) -> None:
        from brasidas.autonomy.areamap import parse_map
        from brasidas.autonomy.planner import BuildCancelled

        revision = int(header["revision"])
        started = time.perf_counter()
        if header["op"] == "map":
            area = parse_map(body)
        else:  # an edit of the map received last (parsed once, not at every edit)
            base, received = int(header["base"]), self.received
            if received is None or received[0] != base:
                if received is None or revision > received[0]:
                    self._send({"op": "resend", "revision": revision})  # the whole map, please
                return
            changes = orjson.loads(body)
            area = received[1].with_keepouts(add=changes["add"], remove=changes["remove"])
        self.received = (revision, area)
        cancelled = threading.Event()
        with self.lock:
            if revision < self.newest_map:
                cancelled.set()
            self.building = (revision, cancelled)
        try:
            if cancelled.is_set():
                raise BuildCancelled("a newer map came")
            planner, incremental = self._planner_for(area, float(header["clearance"]), cancelled)
        except BuildCancelled:
            self._send({"op": "dropped", "revision": revision})
            return
        finally:
            with self.lock:
                self.building = None
        self.revision, self.area, self.planner = revision, area, planner
        self._send(
            {
                "op": "ready",
                "revision": revision,
                "build_s": time.perf_counter() - started,
                "nodes": len(planner.nodes),
                "edges": planner.edge_count,
                "incremental": incremental,
            }
        )

    def _planner_for(self, area: Any, clearance: float, cancelled: threading.Event) -> Any:
        """The last graph changed by the keep-outs added and removed, when it is the same
        boundary and clearance and a few changes; else a new graph."""
        import shapely
        import shapely.errors

        from brasidas.autonomy.planner import Planner

        before, planner = self.area, self.planner
        if (
            planner is not None
            and planner.clearance == clearance
            and before.boundary.equals_exact(area.boundary, 0.0)
        ):
            common = [key for key in area.keepouts if key in before.keepouts]
            same = shapely.equals_exact(
                [before.keepouts[key] for key in common],
                [area.keepouts[key] for key in common],
                0.0,
            )
            kept = {key for key, equal in zip(common, same.tolist(), strict=True) if equal}
            removed = [key for key in before.keepouts if key not in kept]
            added = {key: zone for key, zone in area.keepouts.items() if key not in kept}
            if len(removed) + len(added) <= INCREMENTAL_MOST:
                try:
                    return planner.changed(added, removed, cancelled), True
                except shapely.errors.GEOSException:
                    # Cut and reopened many times (the lidar's keep-outs coming and going),
                    # the free space can gather slivers GEOS cannot difference ("Ring edge
                    # missing"): build it again from the map (the answer says not incremental).
                    pass
        return Planner(area.boundary, area.keepouts, clearance, cancelled), False

    def _plan(self, header: dict[str, Any]) -> None:
        from brasidas.autonomy.planner import Unreachable

        revision, request = int(header["revision"]), header["id"]
        answer: dict[str, Any] = {"revision": revision, "id": request}
        if revision != self.revision or self.planner is None:
            self._send({"op": "stale", **answer})
            return
        start, goal = header["start"], header["goal"]
        started = time.perf_counter()
        answer["plan_s"] = 0.0
        try:
            path = self.planner.plan(
                (float(start[0]), float(start[1])), (float(goal[0]), float(goal[1]))
            )
        except Unreachable as exc:
            answer["plan_s"] = time.perf_counter() - started
            self._send({"op": "unreachable", "reason": str(exc), **answer})
            return
        answer["plan_s"] = time.perf_counter() - started
        self._send({"op": "path", "points": [list(p) for p in path.points], **answer})


def _die_with_parent() -> None:
    """Linux: killed when the platform dies (even by SIGKILL; prctl names the thread that
    started it, the event loop's), not only when the reader
    thread gets the socket's end, which waits for the GIL a long block may hold."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    parent = os.getppid()
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent:  # the platform died before prctl
        os._exit(0)


def main(argv: list[str]) -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the platform stops it, not a terminal's ^C
    _die_with_parent()
    with contextlib.suppress(OSError):
        os.nice(NICENESS)
    sock = socket.socket(fileno=int(argv[1]))
    sock.setblocking(True)
    worker = _Worker(sock)
    threading.Thread(target=worker.read, name="planner:reader", daemon=True).start()
    worker.serve()
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv))
