"""``make bench``: run every ``bench/bench_*.py`` and print its figures, then all of them as JSON.

Benchmarks measure; they do not gate CI. Each module exposes ``async def run() -> dict``.
"""

from __future__ import annotations

import asyncio
import importlib
import json
import os
import sys
import time
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent


def main(argv: list[str]) -> int:
    argv = _options(argv)
    selected = set(argv)
    os.environ.setdefault("XDG_STATE_HOME", str(HERE / "results" / "state"))
    results: dict[str, dict[str, object]] = {}
    for path in sorted(HERE.glob("bench_*.py")):
        name = path.stem.removeprefix("bench_")
        if selected and name not in selected:
            continue
        print(f"== {name}", flush=True)
        started = time.monotonic()
        try:
            module = importlib.import_module(f"bench.{path.stem}")
            figures = asyncio.run(module.run())
        except Exception as err:
            traceback.print_exc()
            figures = {"error": f"{type(err).__name__}: {err}"}
        figures["bench_seconds"] = round(time.monotonic() - started, 1)
        for key, value in figures.items():
            print(f"   {key:<44} {value}")
        results[name] = figures
    (HERE / "results").mkdir(exist_ok=True)
    text = json.dumps(results, indent=2, sort_keys=True, allow_nan=False)
    (HERE / "results" / "latest.json").write_text(text + "\n")
    print("\nJSON:")
    print(text)
    return 0


def _options(argv: list[str]) -> list[str]:
    """``--seconds N``, ``--rows a,b`` and ``--laps N`` for the benchmarks that read them
    (BENCH_SECONDS, BENCH_ROWS: bench_lossy; BENCH_LAPS: bench_town); the rest are benchmark
    names."""
    names: list[str] = []
    words = iter(argv)
    for word in words:
        if word in ("--seconds", "--rows", "--laps"):
            os.environ[f"BENCH_{word[2:].upper()}"] = next(words, "")
        else:
            names.append(word)
    return names


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
