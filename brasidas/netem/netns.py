"""A test network of Linux network namespaces: hosts on one bridge, some behind a link emulator.

:class:`TestNetwork` builds a switch namespace holding a bridge and, per host, a namespace
whose ``eth0`` is one end of a veth pair. A plain host's other end is a bridge port; an
*impaired* host's other end is bridged to its port by a :class:`~brasidas.netem.relay.FrameRelay`
(a userspace bridge port), which drops, delays, reorders, duplicates or cuts its frames.
Nothing touches the machine's own interfaces: everything lives in namespaces named
``bnx<pid>-…``, removed by :meth:`TestNetwork.close`; a crashed run's leftovers (their pid
gone) are removed by :func:`clean_stale` before a new network is built. Addresses come from
TEST-NET-2 (198.51.100.0/24, RFC 5737), so traffic can only be between these namespaces.

:meth:`Host.spawn` runs a command in a host's namespace (``ip netns exec``) that dies with
the process that started it; :func:`socket_in` makes a socket inside a namespace, so a test
can talk to a daemon's loopback-only API or play a third host without a process of its own.
"""

from __future__ import annotations

import contextlib
import ctypes
import ipaddress
import os
import re
import shutil
import signal
import socket
import subprocess
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO

from brasidas.netem.core import Profile
from brasidas.netem.relay import FrameRelay

PREFIX = "bnx"
SUBNET = ipaddress.ip_network("198.51.100.0/24")
"""TEST-NET-2: documentation addresses, never routed anywhere."""
BROADCAST = str(SUBNET.broadcast_address)
NETNS_DIR = Path("/var/run/netns")
_CLONE_NEWNET = 0x40000000
_NAME = re.compile(rf"^{PREFIX}(\d+)-")


class NetnsUnavailable(RuntimeError):
    """This machine (or user) cannot create network namespaces; the message says why."""


def _ip(*args: str, batch: Sequence[str] = ()) -> None:
    """Run ``ip ARGS`` (with ``batch`` lines on stdin for ``-b -``); raise with its stderr."""
    result = subprocess.run(
        ["ip", *args], input="".join(f"{line}\n" for line in batch), text=True, capture_output=True
    )
    if result.returncode != 0:
        raise RuntimeError(f"ip {' '.join(args)}: {result.stderr.strip()}")


def unavailable_reason() -> str | None:
    """Why namespaces cannot be created here, or None when they can (the check makes one)."""
    if shutil.which("ip") is None:
        return "network namespace tests need iproute2's 'ip' (apt-get install iproute2)"
    if os.geteuid() != 0:
        return "network namespace tests need root (CAP_NET_ADMIN and CAP_SYS_ADMIN): skipped"
    probe = f"{PREFIX}{os.getpid()}-probe"
    try:
        _ip("netns", "add", probe)
    except RuntimeError as err:
        return f"cannot create a network namespace here: {err}"
    _ip("netns", "del", probe)
    return None


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def _namespaces() -> list[str]:
    result = subprocess.run(["ip", "netns", "list"], text=True, capture_output=True)
    return [line.split()[0] for line in result.stdout.splitlines() if line.strip()]


def _kill_namespace(name: str) -> None:
    """Kill what still runs in namespace ``name``, then delete it."""
    result = subprocess.run(["ip", "netns", "pids", name], text=True, capture_output=True)
    for pid in result.stdout.split():
        with contextlib.suppress(ProcessLookupError, ValueError):
            os.kill(int(pid), signal.SIGKILL)
    subprocess.run(["ip", "netns", "del", name], capture_output=True)


def clean_stale() -> list[str]:
    """Remove the namespaces of earlier runs whose process is gone; returns their names."""
    stale = []
    for name in _namespaces():
        match = _NAME.match(name)
        if match and not _pid_alive(int(match.group(1))):
            _kill_namespace(name)
            stale.append(name)
    return stale


@contextlib.contextmanager
def inside(namespace: str) -> Iterator[None]:
    """Run the block with this thread in ``namespace`` (sockets made here stay in it)."""
    libc = ctypes.CDLL(None, use_errno=True)
    home = os.open("/proc/thread-self/ns/net", os.O_RDONLY)
    target = os.open(NETNS_DIR / namespace, os.O_RDONLY)
    try:
        if libc.setns(target, _CLONE_NEWNET) != 0:
            raise OSError(ctypes.get_errno(), f"setns {namespace}")
        try:
            yield
        finally:
            if libc.setns(home, _CLONE_NEWNET) != 0:  # pragma: no cover - cannot fail as root
                raise OSError(ctypes.get_errno(), "setns back")
    finally:
        os.close(target)
        os.close(home)


def socket_in(
    namespace: str, family: int = socket.AF_INET, kind: int = socket.SOCK_STREAM, proto: int = 0
) -> socket.socket:
    """A socket living in ``namespace`` (usable from any thread afterwards)."""
    with inside(namespace):
        return socket.socket(family, kind, proto)


def _die_with_parent() -> None:  # runs in the child between fork and exec
    libc = ctypes.CDLL(None)
    libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG: a crashed test leaves no daemon


@dataclass
class Host:
    name: str
    namespace: str
    address: str
    relay: FrameRelay | None = None
    """The link emulator between this host and the bridge (impaired hosts only)."""
    processes: list[subprocess.Popen[bytes]] = field(default_factory=list)

    def spawn(
        self,
        argv: Sequence[str],
        *,
        env: dict[str, str] | None = None,
        stdout: IO[bytes] | int | None = subprocess.DEVNULL,
        stderr: IO[bytes] | int | None = None,
    ) -> subprocess.Popen[bytes]:
        """Start ``argv`` in this host's namespace; stopped by :meth:`TestNetwork.close`."""
        process = subprocess.Popen(
            ["ip", "netns", "exec", self.namespace, *argv],
            env=env,
            stdin=subprocess.DEVNULL,
            stdout=stdout,
            stderr=stderr,
            preexec_fn=_die_with_parent,
        )
        self.processes.append(process)
        return process

    def stop_processes(self, timeout: float = 5.0) -> None:
        """SIGTERM each process, then SIGKILL what is left after ``timeout``."""
        for process in self.processes:
            if process.poll() is None:
                process.send_signal(signal.SIGTERM)
        deadline = time.monotonic() + timeout
        for process in self.processes:
            try:
                process.wait(max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
        self.processes.clear()

    def socket(self, family: int = socket.AF_INET, kind: int = socket.SOCK_STREAM) -> socket.socket:
        return socket_in(self.namespace, family, kind)


class TestNetwork:
    """A bridge and hosts on 198.51.100.0/24; ``close()`` removes it all (idempotent)."""

    __test__ = False  # not a pytest class

    def __init__(self, tag: str = "net", *, seed: int = 0) -> None:
        clean_stale()
        self.base = f"{PREFIX}{os.getpid()}-{tag}"
        self.switch = f"{self.base}-sw"
        self.seed = seed
        self.hosts: dict[str, Host] = {}
        self._namespaces: list[str] = []
        self._next = 1
        self.closed = False
        self._add_namespace(self.switch)
        _ip(
            "-n", self.switch, "-b", "-", batch=["link add name br0 type bridge", "link set br0 up"]
        )

    def _add_namespace(self, name: str) -> None:
        if len(name) > 200:
            raise ValueError(f"namespace name too long: {name}")
        _ip("netns", "add", name)
        self._namespaces.append(name)

    def add_host(self, name: str, *, impaired: bool = False, extra_addresses: int = 0) -> Host:
        """A host on the bridge (behind a link emulator when ``impaired``)."""
        index = self._next
        self._next += 1 + extra_addresses
        namespace = f"{self.base}-{name}"
        self._add_namespace(namespace)
        address = str(SUBNET.network_address + index)
        port = f"p{index}"
        if impaired:
            near, far = f"r{index}a", f"r{index}b"
            switch_lines = [
                f"link add name {near} type veth peer name eth0 netns {namespace}",
                f"link add name {far} type veth peer name {port}",
                f"link set {port} master br0",
                *(f"link set {dev} up" for dev in (near, far, port)),
            ]
        else:
            switch_lines = [
                f"link add name {port} type veth peer name eth0 netns {namespace}",
                f"link set {port} master br0",
                f"link set {port} up",
            ]
        _ip("-n", self.switch, "-b", "-", batch=switch_lines)
        host_lines = [
            "link set lo up",
            f"addr add {address}/{SUBNET.prefixlen} broadcast {BROADCAST} dev eth0",
            *(
                f"addr add {SUBNET.network_address + index + 1 + n}/{SUBNET.prefixlen} dev eth0"
                for n in range(extra_addresses)
            ),
            "link set eth0 up",
        ]
        _ip("-n", namespace, "-b", "-", batch=host_lines)
        host = Host(name, namespace, address)
        if impaired:
            # Host to bridge is "up", bridge to host "down"; each direction its own seed.
            with inside(self.switch):
                host.relay = FrameRelay(near, far, seed=self.seed + index, name=name)
            host.relay.start()
        self.hosts[name] = host
        return host

    def addresses_of(self, host: Host, count: int) -> list[str]:
        """The ``count`` addresses added after ``host``'s own (``add_host(extra_addresses=)``)."""
        first = ipaddress.ip_address(host.address)
        return [str(first + 1 + n) for n in range(count)]

    def impair(self, host: str, down: Profile | None = None, up: Profile | None = None) -> None:
        """Set the emulated link of ``host``: ``down`` bridge→host, ``up`` host→bridge."""
        relay = self.hosts[host].relay
        if relay is None:
            raise ValueError(f"{host} is not behind a link emulator")
        relay.set_profiles(down=down, up=up)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        for host in self.hosts.values():
            host.stop_processes()
            if host.relay is not None:
                host.relay.close()
        for namespace in reversed(self._namespaces):
            _kill_namespace(namespace)

    def __enter__(self) -> TestNetwork:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
