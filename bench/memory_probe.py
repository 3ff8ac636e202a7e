"""``python -m bench.memory_probe [--frames N] [--report FILE] -- PLATFORM ARGS``: a platform
daemon (as ``python -m platformd``) with a thread reporting its memory.

Every ``--interval`` seconds one JSON line on stdout: ``t`` (monotonic s), ``rss_kb`` (of which
``rss_anon_kb`` anonymous, ``rss_file_kb`` file pages: libraries' code as it is first run), where the
memory is (:func:`native`: glibc malloc's in-use and free bytes over all its arenas, the private
dirty KiB of each kind of anonymous mapping, pymalloc's allocated blocks, the collections each
generation of the garbage collector has run; not ``gc.get_objects()``: the list it makes holds a
tuple another thread is building from a generator, whose shrinking then fails with SystemError,
which crashed the telemetry actor once)
and, with ``--frames`` > 0 (tracemalloc on, that many frames a trace), ``traced`` (bytes Python
holds). ``--trim`` calls glibc's ``malloc_trim(0)`` before each line (to tell fragmentation
from growth: it returns malloc's free pages to the system).
With ``--report``, that file is rewritten at each line with the allocation sites that grew the
most since the first line after ``--baseline`` seconds (tracemalloc snapshots compared).
A line ``snapshot PATH`` on stdin dumps a tracemalloc snapshot there, then prints
``{"snapshot": PATH}``; with ``--trace-when-told`` tracemalloc starts at a line ``trace``
(then prints ``{"tracing": true}``): the start-up runs at full speed and is not traced.
"""

from __future__ import annotations

import argparse
import collections
import ctypes
import gc
import json
import os
import re
import sys
import tempfile
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


def _status() -> dict[str, int]:
    """The KiB figures of ``/proc/self/status`` (VmRSS = RssAnon + RssFile + RssShmem)."""
    out = {}
    for line in Path("/proc/self/status").read_text().splitlines():
        key, _, value = line.partition(":")
        if value.strip().endswith("kB"):
            out[key] = int(value.split()[0])
    return out


class _MallInfo2(ctypes.Structure):
    _fields_ = [
        (name, ctypes.c_size_t)
        for name in (
            "arena", "ordblks", "smblks", "hblks", "hblkhd",
            "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost",
        )
    ]  # fmt: skip


_LIBC = ctypes.CDLL("libc.so.6")
_LIBC.mallinfo2.restype = _MallInfo2
_LIBC.malloc_trim.argtypes = [ctypes.c_size_t]


def native() -> dict[str, object]:
    """glibc malloc's view (all arenas) and the kernel's: in use vs free inside malloc's heaps,
    private dirty / anonymous memory, and how many heap mappings (arenas) there are."""
    info = _LIBC.mallinfo2()
    out: dict[str, object] = {
        "m_inuse_kb": info.uordblks // 1024,
        "m_free_kb": info.fordblks // 1024,
        "m_mmap_kb": info.hblkhd // 1024,
        "m_heap_kb": info.arena // 1024,
    }
    for line in Path("/proc/self/smaps_rollup").read_text().splitlines():
        key, _, value = line.partition(":")
        if key in ("Private_Dirty", "Anonymous"):
            out[key.lower() + "_kb"] = int(value.split()[0])
    out.update(_anonymous_by_kind())
    out["py_blocks"] = sys.getallocatedblocks()
    out["gc_runs"] = [generation["collections"] for generation in gc.get_stats()]
    out["gc_frozen"] = gc.get_freeze_count()
    return out


def _anonymous_by_kind() -> dict[str, object]:
    """Private dirty KiB of the anonymous mappings by kind: malloc's main heap, its other arenas
    (64 MiB-aligned heaps), pymalloc's 1 MiB arenas, thread stacks (8 MiB), the rest."""
    kinds = dict.fromkeys(("heap", "arena", "pyarena", "stack", "other"), 0)
    count = dict.fromkeys(kinds, 0)
    kind = ""
    for line in Path("/proc/self/smaps").read_text().splitlines():
        head = line.split()
        if "-" in head[0] and len(head) >= 5 and ":" not in head[0]:
            start, end = (int(x, 16) for x in head[0].split("-"))
            size = end - start
            name = head[5] if len(head) > 5 else ""
            if name == "[heap]":
                kind = "heap"
            elif name or head[1] != "rw-p":
                kind = ""
            elif start % (64 << 20) == 0:
                kind = "arena"
            elif size == 1 << 20:  # adjacent ones merge into one mapping: counted as "other"
                kind = "pyarena"
            elif size in (8 << 20, (8 << 20) - 4096):  # a guard page below a thread's stack
                kind = "stack"
            else:
                kind = "other"
            if kind:
                count[kind] += 1
        elif kind and head[0] == "Private_Dirty:":
            kinds[kind] += int(head[1])
    return {
        **{f"a_{kind}_kb": size for kind, size in kinds.items()},
        **{f"n_{kind}": number for kind, number in count.items()},
    }


_FREE_LIST = re.compile(r"(\d+) free (?:(\d+)-sized )?(Py\w+?)s? \* \d+ bytes each = +([\d,]+)")
_SIZE_CLASS = re.compile(r" *(\d+) +(\d+) +(\d+) +(\d+) +(\d+)$")


def mallocstats() -> dict[str, object]:
    """What ``sys._debugmallocstats()`` writes to the C stderr, parsed: blocks in use per size
    class, the bytes on each kind of free list, pymalloc's arenas and allocated bytes."""
    with tempfile.TemporaryFile("w+") as out:
        saved = os.dup(2)
        try:
            sys.stderr.flush()
            os.dup2(out.fileno(), 2)
            sys._debugmallocstats()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        out.seek(0)
        text = out.read()
    classes = [0] * 32
    free: collections.Counter[str] = collections.Counter()
    tuples = [0] * 20
    stats: dict[str, object] = {}
    for line in text.splitlines():
        if match := _SIZE_CLASS.match(line):
            index, _size, _pools, used, _avail = (int(x) for x in match.groups())
            if index < len(classes):
                classes[index] = used
        elif match := _FREE_LIST.search(line):
            count, size, kind, total = match.groups()
            free[kind.removeprefix("Py").removesuffix("Object").lower()] += int(
                total.replace(",", "")
            )
            if size and 0 < int(size) <= len(tuples):
                tuples[int(size) - 1] = int(count)
        elif line.startswith("# arenas allocated current"):
            stats["py_arenas"] = int(line.split("=")[1].replace(",", ""))
        elif line.startswith("# bytes in allocated blocks"):
            stats["py_alloc_b"] = int(line.split("=")[1].replace(",", ""))
    stats["cls_blocks"] = classes
    stats["fl_tuples"] = tuples  # how many tuples of 1..20 items each free list holds
    stats.update({f"fl_{kind}_b": size for kind, size in sorted(free.items())})
    stats["fl_b"] = sum(free.values())
    return stats


def _report(args: argparse.Namespace) -> None:
    baseline: tracemalloc.Snapshot | None = None
    started = time.monotonic()
    while True:
        time.sleep(args.interval)
        if args.frames and not tracemalloc.is_tracing():
            if not args.trace_when_told and time.monotonic() - started >= args.trace_from:
                tracemalloc.start(args.frames)
            continue
        collected: dict[str, object] = {}
        if args.collect:
            gc.set_debug(gc.DEBUG_SAVEALL)
            collected["collected"] = gc.collect()
            gc.set_debug(0)
            kinds = collections.Counter(type(thing).__qualname__ for thing in gc.garbage)
            collected["garbage"] = kinds.most_common(8)
            gc.garbage.clear()
        if args.trim:
            _LIBC.malloc_trim(0)
        status = _status()
        line: dict[str, object] = {
            "t": round(time.monotonic(), 3),
            "rss_kb": status.get("VmRSS", 0),
            "rss_anon_kb": status.get("RssAnon", 0),
            "rss_file_kb": status.get("RssFile", 0),
        }
        line.update(collected)
        line.update(native())
        if args.mallocstats:
            line.update(mallocstats())
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


def _commands(frames: int) -> None:
    for line in sys.stdin:
        command, _, path = line.strip().partition(" ")
        if command == "trace" and frames:
            if not tracemalloc.is_tracing():
                tracemalloc.start(frames)
            _say({"tracing": True})
        if command == "snapshot" and path and tracemalloc.is_tracing():
            gc.collect()  # what is only waiting for the cycle collector is not growth
            tracemalloc.take_snapshot().dump(path)
            _say({"snapshot": path})


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.memory_probe")
    parser.add_argument("--interval", type=float, default=5.0)
    parser.add_argument("--frames", type=int, default=0, help="tracemalloc frames (0: off)")
    parser.add_argument("--report", default="", help="where to write the growth report")
    parser.add_argument("--collect", action="store_true", help="gc.collect() before each line")
    parser.add_argument("--trim", action="store_true", help="malloc_trim(0) before each line")
    parser.add_argument(
        "--mallocstats", action="store_true", help="pymalloc size classes and free lists"
    )
    parser.add_argument(
        "--trace-from",
        type=float,
        default=0.0,
        help="start tracemalloc this many seconds in (a fast start; only what is allocated "
        "after is traced)",
    )
    parser.add_argument(
        "--trace-when-told",
        action="store_true",
        help="start tracemalloc at a 'trace' line on stdin (after the start-up)",
    )
    parser.add_argument("--baseline", type=float, default=60.0, help="seconds of warm-up")
    args, platform_args = parser.parse_known_args()
    if platform_args[:1] == ["--"]:
        platform_args = platform_args[1:]
    if args.frames and not args.trace_from and not args.trace_when_told:
        tracemalloc.start(args.frames)
    sys.argv = ["brasidas-platform", *platform_args]
    threading.Thread(target=_report, args=(args,), name="memory-probe", daemon=True).start()
    threading.Thread(
        target=_commands, args=(args.frames,), name="memory-probe-commands", daemon=True
    ).start()
    from platformd.__main__ import run

    return run()


if __name__ == "__main__":
    sys.exit(main())
