"""``make net-demo``: the test network by hand, a station and two platforms, a link to play with.

Builds the namespaces the tests use: ``station`` and ``rover1`` (behind the link emulator)
and ``rover2`` (beacons to a multicast group), starts ``brasidas-station serve`` and two
``brasidas-platform --sim`` on them, prints how to reach them, then reads commands that change
rover1's link (``loss 10``, ``delay 50 20``, ``cut``, ``restore``, ``stats``, ...). Ctrl-C or
``quit`` removes everything.
"""

from __future__ import annotations

import argparse
import contextlib
import shlex
import sys
import tempfile
from pathlib import Path

from brasidas import security
from brasidas.netem import mesh
from brasidas.netem.core import Profile
from brasidas.netem.netns import BROADCAST, TestNetwork, unavailable_reason
from brasidas.netem.relay import FrameRelay

HELP = """commands (rover1's link, station to rover1 unless 'up' is given first):
  loss PCT | delay MS [JITTER_MS] | reorder PCT | duplicate PCT   e.g. 'loss 10', 'up loss 5'
  rate KBPS (a capacity limit, 0: none)                            e.g. 'up rate 500'
  cut | restore | clear | stats | help | quit"""


def _apply(relay: FrameRelay, words: list[str]) -> str:
    direction = "down"
    if words and words[0] in ("up", "down"):
        direction, words = words[0], words[1:]
    if not words:
        return HELP
    command, numbers = words[0], [float(w) for w in words[1:]]
    link = relay.links[direction]
    profile = link.profile
    fields = profile.__dict__.copy()
    if command == "cut":
        relay.cut()
        return "link cut (both directions)"
    if command == "restore":
        relay.restore()
        return "link restored"
    if command == "clear":
        relay.clear()
        return "clean link both ways"
    if command == "stats":
        return "\n".join(f"{k}: {v}" for k, v in relay.stats().items())
    if command in ("loss", "reorder", "duplicate") and len(numbers) == 1:
        fields[command] = numbers[0] / 100
    elif command == "rate" and len(numbers) == 1:
        fields["rate_kbps"] = numbers[0]
    elif command == "delay" and numbers:
        fields["delay"] = numbers[0] / 1000
        fields["jitter"] = numbers[1] / 1000 if len(numbers) > 1 else 0.0
    else:
        return HELP
    new = Profile(**fields)
    relay.set_profiles(**{direction: new})
    return f"{direction}: {new.describe()}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m brasidas.netem", description=__doc__)
    parser.add_argument("--seed", type=int, default=0, help="the link emulator's random seed")
    args = parser.parse_args(argv)
    reason = unavailable_reason()
    if reason is not None:
        print(reason, file=sys.stderr)
        return 1
    scratch = Path(tempfile.mkdtemp(prefix="brasidas-net-demo-"))
    key_file = scratch / "fleet.key"
    security.generate_key(key_file)
    processes = []
    with TestNetwork("demo", seed=args.seed) as net:
        station = net.add_host("station")
        rover1 = net.add_host("rover1", impaired=True)
        rover2 = net.add_host("rover2")
        logs = []

        def spawn(host_name: str, name: str, command: list[str]) -> None:
            log = (scratch / f"{name}.log").open("wb")
            logs.append(log)
            processes.append(
                net.hosts[host_name].spawn([sys.executable, *command], stderr=log, stdout=log)
            )

        spawn(
            "rover1",
            "rover-1",
            mesh.platform_argv(rover1.address, "rover-1", str(key_file), [BROADCAST]),
        )
        spawn(
            "rover2",
            "rover-2",
            mesh.platform_argv(
                rover2.address,
                "rover-2",
                str(key_file),
                [mesh.MULTICAST_GROUP],
                "navcam.enabled=false",
            ),
        )
        spawn(
            "station",
            "station-1",
            mesh.station_argv(
                "station-1", str(key_file), f'discovery.groups=["{mesh.MULTICAST_GROUP}"]'
            ),
        )
        exec_in = f"ip netns exec {station.namespace}"
        venv = Path(sys.executable).parent
        print(
            f"""network 198.51.100.0/24 on a bridge in namespace {net.switch}:
  station  {station.address}  ({station.namespace})  brasidas-station serve, key {key_file}
  rover1   {rover1.address}  ({rover1.namespace})  platform --sim, beacons to {BROADCAST},
           behind the link emulator (seed {args.seed})
  rover2   {rover2.address}  ({rover2.namespace})  platform --sim, beacons to {mesh.MULTICAST_GROUP}
logs in {scratch}

try, in another terminal:
  {exec_in} {venv}/brasidas-station list --set security.key_file={key_file} \\
      --set 'discovery.groups=["{mesh.MULTICAST_GROUP}"]'
  {exec_in} {venv}/brasidas-station drive rover-1
  {exec_in} {venv}/brasidas-station status rover-1 --watch

{HELP}""",
            flush=True,
        )
        assert rover1.relay is not None
        try:
            for line in sys.stdin:
                words = shlex.split(line)
                if not words:
                    continue
                if words[0] in ("quit", "exit"):
                    break
                try:
                    print(_apply(rover1.relay, words), flush=True)
                except ValueError as err:
                    print(f"error: {err}", flush=True)
        except KeyboardInterrupt:
            pass
        print("removing the network", flush=True)
        for log in logs:
            with contextlib.suppress(OSError):
                log.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
