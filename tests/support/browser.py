"""One headless Chromium per test worker, which every browser test connects to over the
DevTools protocol (``browser`` in conftest.py) with a fresh context per page: a launch per test
cost a Chromium start and exit each time.

Started as Playwright would start it (its switches for automation, below), with the one argument
list every browser test needs: a fake microphone for push-to-talk, its permission granted, and
``station.test`` resolving to loopback for the TLS test.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import signal
import subprocess
import time
from pathlib import Path

CHROMIUM = shutil.which("chromium-headless-shell") or "/usr/bin/chromium-headless-shell"
"""Chromium's headless shell (Debian's ``chromium-headless-shell``, what Playwright itself runs
headless): the same Blink, V8 and WebCodecs without the browser's own UI layers. Measured on
the 34 browser tests: 153 s at load 4 against 201 s quiet with the full ``chromium --headless``,
and on three modules 14 CPU-s against 25. (``make bench console`` keeps the full browser: the
glass-to-glass an operator's browser shows.)"""
CHROMIUM_ARGS = [
    "--no-sandbox",  # tests run as root
    "--disable-gpu",
    "--no-first-run",
    "--disable-sync",
    "--disable-background-networking",
    "--disable-component-update",
    "--use-fake-device-for-media-stream",  # a beeping microphone for push-to-talk
    "--use-fake-ui-for-media-stream",  # its permission granted
    "--host-resolver-rules=MAP station.test 127.0.0.1",
]
"""The one argument list of every browser test."""

AUTOMATION_ARGS = [
    # What Playwright's own launch passes: pages keep their timers and rendering when not in
    # front, and nothing of the browser's own starts in the background.
    "--headless",
    "--hide-scrollbars",
    "--mute-audio",
    "--disable-background-timer-throttling",
    "--disable-backgrounding-occluded-windows",
    "--disable-renderer-backgrounding",
    "--disable-back-forward-cache",
    "--disable-breakpad",
    "--disable-dev-shm-usage",
    "--disable-extensions",
    "--disable-hang-monitor",
    "--disable-ipc-flooding-protection",
    "--disable-popup-blocking",
    "--disable-prompt-on-repost",
    "--no-default-browser-check",
    "--force-color-profile=srgb",
    "--password-store=basic",
    "--use-mock-keychain",
    "--enable-automation",
]

START_TIMEOUT_S = 30.0


class SharedChromium:
    """The worker's Chromium, started on first use and again if it died."""

    def __init__(self, directory: Path) -> None:
        self.directory = directory
        self.process: subprocess.Popen[bytes] | None = None
        self._endpoint = ""

    def endpoint(self) -> str:
        """The running Chromium's DevTools address (``http://127.0.0.1:PORT``)."""
        if self.process is None or self.process.poll() is not None:
            self._start()
        return self._endpoint

    def _start(self) -> None:
        profile = self.directory / f"profile-{time.monotonic_ns()}"
        port_file = profile / "DevToolsActivePort"
        with open(self.directory / "chromium.log", "ab") as log:
            self.process = subprocess.Popen(
                [
                    CHROMIUM,
                    *AUTOMATION_ARGS,
                    *CHROMIUM_ARGS,
                    "--remote-debugging-port=0",  # the kernel's choice, written to the profile
                    f"--user-data-dir={profile}",
                    "about:blank",
                ],
                stdin=subprocess.DEVNULL,
                stdout=log,
                stderr=log,
                # A group of its own, ended whole (close): Debian's chromium-headless-shell is
                # a shell script that does not exec the browser, so ending the script alone
                # left the browser and its helpers running, one set per test worker and run.
                start_new_session=True,
            )
        deadline = time.monotonic() + START_TIMEOUT_S
        while not (port_file.exists() and port_file.read_text().strip()):
            if self.process.poll() is not None or time.monotonic() > deadline:
                self.close()
                log_text = (self.directory / "chromium.log").read_text(errors="replace")
                raise RuntimeError(f"Chromium did not start:\n{log_text[-2000:]}")
            time.sleep(0.02)
        port = port_file.read_text().split()[0]
        self._endpoint = f"http://127.0.0.1:{port}"

    def close(self) -> None:
        process, self.process = self.process, None
        if process is None:
            return
        _signal_group(process, signal.SIGTERM)
        try:
            process.wait(10)
        except subprocess.TimeoutExpired:
            _signal_group(process, signal.SIGKILL)
            process.wait()
        # The browser itself, under the script: its group outlives the script by a moment.
        deadline = time.monotonic() + 10
        while _group_alive(process.pid) and time.monotonic() < deadline:
            time.sleep(0.02)
        if _group_alive(process.pid):
            _signal_group(process, signal.SIGKILL)


def _signal_group(process: subprocess.Popen[bytes], signum: int) -> None:
    with contextlib.suppress(ProcessLookupError):
        os.killpg(process.pid, signum)


def _group_alive(group: int) -> bool:
    try:
        os.killpg(group, 0)
    except ProcessLookupError:
        return False
    return True
