"""``python -m bench.memory_probe [--frames N] [--report FILE] -- PLATFORM ARGS``: a platform
daemon (as ``python -m platformd``) with a thread reporting its memory.

Every ``--interval`` seconds one JSON line on stdout: ``t`` (monotonic s), ``rss_kb`` and, with
``--frames`` > 0 (tracemalloc on, that many frames a trace), ``traced`` (bytes Python holds).
With ``--report``, that file is rewritten at each line with the allocation sites that grew the
most since the first line after ``--baseline`` seconds (tracemalloc snapshots compared).
A line ``snapshot PATH`` on stdin dumps a tracemalloc snapshot there, then prints
``{"snapshot": PATH}``.
"""

from __future__ import annotations

import argparse
import gc
import json
import sys
import threading
import time
import tracemalloc
from pathlib import Path

_OUT = threading.Lock()


def _say(line: dict[str, object]) -> None:
    """One JSON line on stdout (two threads write: one line at a time)."""
    with _OUT:
        sys.stdout.write(json.dumps(line) + "\n")
        sys.stdout.flush()


def rss_kb() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def _report(args: argparse.Namespace) -> None:
    baseline: tracemalloc.Snapshot | None = None
    started = time.monotonic()
    while True:
        time.sleep(args.interval)
        line: dict[str, object] = {"t": round(time.monotonic(), 3), "rss_kb": rss_kb()}
        if args.frames:
            line["traced"] = tracemalloc.get_traced_memory()[0]
        _say(line)
        if not (args.frames and args.report):
            continue
        if time.monotonic() - started < args.baseline:
            continue
        snapshot = tracemalloc.take_snapshot().filter_traces(
            [tracemalloc.Filter(False, tracemalloc.__file__)]
        )
        if baseline is None:
            baseline = snapshot
            continue
        grown = snapshot.compare_to(baseline, "traceback")[:15]
        text = [f"after {time.monotonic() - started:.0f} s"]
        for stat in grown:
            text.append(f"\n{stat.size_diff / 1024:+.1f} KiB {stat.count_diff:+d} blocks")
            text.extend(f"    {frame}" for frame in stat.traceback.format()[-2 * args.frames :])
        Path(args.report).write_text("\n".join(text) + "\n")


def _commands() -> None:
    for line in sys.stdin:
        command, _, path = line.strip().partition(" ")
        if command == "snapshot" and path and tracemalloc.is_tracing():
            gc.collect()  # what is only waiting for the cycle collector is not growth
            tracemalloc.take_snapshot().dump(path)
            _say({"snapshot": path})


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.memory_probe")
    parser.add_argument("--interval", type=float, default=5.0)
    parser.add_argument("--frames", type=int, default=0, help="tracemalloc frames (0: off)")
    parser.add_argument("--report", default="", help="where to write the growth report")
    parser.add_argument("--baseline", type=float, default=60.0, help="seconds of warm-up")
    args, platform_args = parser.parse_known_args()
    if platform_args[:1] == ["--"]:
        platform_args = platform_args[1:]
    if args.frames:
        tracemalloc.start(args.frames)
    sys.argv = ["brasidas-platform", *platform_args]
    threading.Thread(target=_report, args=(args,), name="memory-probe", daemon=True).start()
    threading.Thread(target=_commands, name="memory-probe-commands", daemon=True).start()
    from platformd.__main__ import run

    return run()


if __name__ == "__main__":
    sys.exit(main())
