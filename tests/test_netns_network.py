"""The test network itself: it says why it cannot run, and a crashed run leaves nothing behind."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import pytest
from netns import requires_netns

from brasidas.netem import netns
from brasidas.netem.netns import clean_stale


def test_without_root_the_reason_is_plain(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(os, "geteuid", lambda: 1000)
    reason = netns.unavailable_reason()
    assert reason is not None
    assert "root" in reason
    assert "CAP_NET_ADMIN" in reason


CRASHING_RUN = """
import time
from brasidas.netem.netns import TestNetwork
net = TestNetwork("crash")
host = net.add_host("h", impaired=True)
daemon = host.spawn(["sleep", "300"])
print(net.base, daemon.pid, flush=True)
time.sleep(300)
"""


@requires_netns
def test_a_crashed_runs_namespaces_and_daemons_are_removed() -> None:
    run = subprocess.Popen([sys.executable, "-c", CRASHING_RUN], stdout=subprocess.PIPE, text=True)
    assert run.stdout is not None
    base, pid = run.stdout.readline().split()
    run.kill()  # no cleanup runs: as a crash
    run.wait()
    run.stdout.close()
    # The daemon dies with the process that started it (PR_SET_PDEATHSIG).
    deadline = time.monotonic() + 10
    while os.path.exists(f"/proc/{pid}") and _state(pid) != "Z":
        assert time.monotonic() < deadline, "daemon outlived its crashed parent"
        time.sleep(0.05)
    left = [name for name in netns._namespaces() if name.startswith(base)]
    assert len(left) == 2  # the switch and the host, left by the crash
    removed = clean_stale()  # what every new TestNetwork does first
    assert set(left) <= set(removed)
    assert not [name for name in netns._namespaces() if name.startswith(base)]


def _state(pid: str) -> str:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0]
    except OSError:
        return "gone"
