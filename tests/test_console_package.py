"""The browser console ships with the package: a built wheel holds every file under web/, an
installed station daemon serves them, and one installed without them refuses to start."""

from __future__ import annotations

import asyncio
import re
import shutil
import subprocess
import sys
import zipfile
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

import aiohttp
import pytest

ROOT = Path(__file__).resolve().parents[1]
BUILD_IGNORE = shutil.ignore_patterns(
    ".*", "build", "*.egg-info", "__pycache__", "tests", "bench", "dist", "node_modules"
)


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The project built into a wheel (from a copy of the tree) and unpacked as pip would
    install it: a directory to put first on ``PYTHONPATH``."""
    work = tmp_path_factory.mktemp("wheel")
    source = work / "source"
    shutil.copytree(ROOT, source, symlinks=True, ignore=BUILD_IGNORE)
    build = subprocess.run(
        [
            *(sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation"),
            *("--wheel-dir", str(work), str(source)),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert build.returncode == 0, (
        f"pip wheel failed (make deps installs its tools):\n{build.stderr}"
    )
    (wheel,) = work.glob("brasidas-*.whl")
    target = work / "site"
    with zipfile.ZipFile(wheel) as archive:
        archive.extractall(target)
    return target


def test_the_wheel_holds_every_console_file(installed: Path) -> None:
    shipped = {
        p.relative_to(installed / "stationd" / "web") for p in installed.glob("stationd/web/**/*")
    }
    written = {p.relative_to(ROOT / "web") for p in (ROOT / "web").glob("**/*")}
    assert {Path("index.html"), Path("console.js"), Path("console.css")} <= written
    assert written <= shipped  # new files under web/ ship too: the rule is a glob


@asynccontextmanager
async def serve(pythonpath: Path) -> AsyncIterator[tuple[asyncio.subprocess.Process, str]]:
    """``brasidas-station serve`` from ``pythonpath``; yields it with its "local API" line."""
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "stationd",
        "serve",
        "--insecure",
        *("--set", "station.api_port=0", "--set", "discovery.port=0"),
        cwd=pythonpath.parent,  # not the source tree: only the installed copy is importable
        env={"PYTHONPATH": str(pythonpath), "PATH": "/usr/bin:/bin", "HOME": str(pythonpath)},
        stdout=asyncio.subprocess.DEVNULL,
        stderr=asyncio.subprocess.PIPE,
    )
    assert process.stderr is not None
    try:
        line = ""
        async with asyncio.timeout(30):
            while "local API http://" not in line:
                line = (await process.stderr.readline()).decode()
                if not line:
                    break
        yield process, line
    finally:
        if process.returncode is None:
            process.terminate()
            await process.wait()


async def test_the_installed_station_serves_its_console(installed: Path) -> None:
    async with serve(installed) as (process, line):
        assert process.returncode is None, "the installed station did not start"
        match = re.search(r"local API (http://127\.0\.0\.1:\d+)", line)
        assert match, line
        async with aiohttp.ClientSession() as session:
            for path, text in (
                ("/", "<html"),
                ("/static/console.js", ""),
                ("/static/console.css", ""),
            ):
                async with session.get(match.group(1) + path) as response:
                    assert response.status == 200, path
                    assert text in (await response.text())
        where = await asyncio.create_subprocess_exec(
            *(sys.executable, "-c", "import stationd.daemon as d; print(d.WEB_ROOT.resolve())"),
            env={"PYTHONPATH": str(installed)},
            cwd=installed,
            stdout=asyncio.subprocess.PIPE,
        )
        out, _ = await asyncio.wait_for(where.communicate(), 30)
        assert Path(out.decode().strip()).is_relative_to(installed)  # not the source tree's


async def test_a_station_installed_without_its_console_refuses_to_start(
    installed: Path, tmp_path: Path
) -> None:
    broken = tmp_path / "site"
    shutil.copytree(installed, broken, ignore=shutil.ignore_patterns("index.html"))
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        "-m",
        "stationd",
        "serve",
        "--insecure",
        *("--set", "station.api_port=0", "--set", "discovery.port=0"),
        cwd=tmp_path,
        env={"PYTHONPATH": str(broken), "PATH": "/usr/bin:/bin", "HOME": str(tmp_path)},
        stdout=asyncio.subprocess.DEVNULL,
        stderr=asyncio.subprocess.PIPE,
    )
    _, err = await asyncio.wait_for(process.communicate(), 30)
    assert process.returncode == 1
    message = err.decode().strip().splitlines()[-1]
    assert message.startswith("brasidas-station: no browser console: ")
    assert "stationd/web/index.html is missing" in message
