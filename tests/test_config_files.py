"""Config and key files an operator (or a mistake) can hand the daemons (issue 19, item 8):
every one ends in one line naming the file and the fix, never a traceback, a hang or a flood;
every numeric key has a range that makes physical sense."""

from __future__ import annotations

import dataclasses
import json
import math
import os
import resource
import subprocess
import sys
import typing
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from brasidas import security
from brasidas.config import ConfigError, PlatformConfig, StationConfig, load_config
from brasidas.config.loader import checks_of
from brasidas.config.platform import SafetySection
from platformd import cli as platform_cli
from platformd.beacon import check_beacon_fits
from platformd.speedcap import compute_cap
from stationd import cli as station_cli

# --------------------------------------------------------------------------- key files


def key_file(tmp_path: Path, mode: int = 0o600, content: bytes | None = None) -> Path:
    path = tmp_path / "fleet.key"
    path.write_bytes(content if content is not None else os.urandom(32).hex().encode() + b"\n")
    path.chmod(mode)
    return path


def platform_main(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, list[str]]:
    code = platform_cli.main(list(argv))
    return code, capsys.readouterr().err.strip().splitlines()


@pytest.mark.parametrize("mode", [0o644, 0o666, 0o640, 0o604, 0o620])
def test_a_key_file_others_can_read_is_refused_naming_the_chmod(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], mode: int
) -> None:
    path = key_file(tmp_path, mode)
    code, err = platform_main(capsys, "--set", f"security.key_file={path}")
    assert code == 2
    assert err == [
        f"brasidas-platform: {path}: permissions {mode:04o} for the fleet key are too open: "
        f"it must be accessible by its owner only (chmod 600 {path}); or pass --insecure"
    ]


def test_a_private_key_file_is_read(tmp_path: Path) -> None:
    key = os.urandom(32)
    path = key_file(tmp_path, 0o400, key.hex().encode())
    assert security.load_key(path) == key


def test_a_key_file_that_is_not_utf8_is_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = key_file(tmp_path, content=b"\xff\xfe" + os.urandom(30))
    code, err = platform_main(capsys, "--set", f"security.key_file={path}")
    assert (code, err) == (
        2,
        [f"brasidas-platform: {path}: fleet key is not hex; or pass --insecure"],
    )


def limited_run(argv: list[str], timeout: float = 60) -> subprocess.CompletedProcess[str]:
    """The platform CLI in a process of its own, its memory capped at 1 GiB (a daemon reading
    /dev/zero to the end fails at the cap, not on the machine), killed after ``timeout``."""

    def cap() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (1 << 30, 1 << 30))

    return subprocess.run(
        [sys.executable, "-m", "platformd", *argv],
        capture_output=True,
        text=True,
        timeout=timeout,
        preexec_fn=cap,
        env={**os.environ, "PYTHONDONTWRITEBYTECODE": "1"},
    )


def test_a_fifo_as_key_file_is_refused_at_once(tmp_path: Path) -> None:
    fifo = tmp_path / "fleet.key"
    os.mkfifo(fifo, 0o600)
    try:
        done = limited_run(["--set", f"security.key_file={fifo}"], timeout=60)
    except subprocess.TimeoutExpired:
        pytest.fail("the platform hung on a FIFO as key file")
    assert done.returncode == 2
    assert f"{fifo}: fleet key is not a regular file (a FIFO)" in done.stderr
    assert "Traceback" not in done.stderr


def test_dev_zero_as_key_file_is_refused(tmp_path: Path) -> None:
    done = limited_run(["--set", "security.key_file=/dev/zero"])
    assert done.returncode == 2, done.stderr[-2000:]
    assert "/dev/zero: fleet key is not a regular file (a character device)" in done.stderr
    assert "Traceback" not in done.stderr


def test_a_huge_key_file_is_refused_unread(tmp_path: Path) -> None:
    path = key_file(tmp_path, content=b"0" * 100_000)
    with pytest.raises(security.FleetKeyError, match="too large|more than"):
        security.load_key(path)


@settings(max_examples=60, deadline=None)
@given(content=st.binary(max_size=300))
def test_any_key_file_content_is_a_key_or_one_clear_error(
    tmp_path_factory: pytest.TempPathFactory, content: bytes
) -> None:
    path = key_file(tmp_path_factory.mktemp("key"), content=content)
    try:
        key = security.load_key(path)
    except security.FleetKeyError as err:
        assert str(err).startswith(f"{path}: ")
        assert "\n" not in str(err)
    else:
        assert len(key) >= 16


def test_the_private_file_rule_is_one_helper_for_any_key(tmp_path: Path) -> None:
    """The rule a MAVLink signing key (or any later secret) reuses, naming what it is."""
    path = key_file(tmp_path, 0o644)
    with pytest.raises(security.PrivateFileError, match="MAVLink signing key are too open"):
        security.read_private_file(path, "MAVLink signing key")
    path.chmod(0o600)
    assert security.read_private_file(path, "MAVLink signing key") == path.read_bytes()


# --------------------------------------------------------------------------- config files


def test_a_config_that_is_not_utf8_is_one_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "platform.toml"
    path.write_bytes(b'[platform]\nid = "rover"\nmodel = "caf\xe9"\n')
    code, err = platform_main(capsys, "--config", str(path), "config")
    assert (code, err) == (
        2,
        [f"brasidas-platform: {path}: not UTF-8 text (byte 0xe9 on line 3)"],
    )


def test_a_fifo_or_device_as_config_is_refused_at_once(tmp_path: Path) -> None:
    fifo = tmp_path / "platform.toml"
    os.mkfifo(fifo)
    for path in (fifo, Path("/dev/zero")):
        try:
            done = limited_run(["--config", str(path), "config"], timeout=60)
        except subprocess.TimeoutExpired:
            pytest.fail(f"the platform hung on {path} as config")
        assert done.returncode == 2, done.stderr[-2000:]
        assert "config is not a regular file" in done.stderr
        assert "Traceback" not in done.stderr


@settings(max_examples=60, deadline=None)
@given(content=st.binary(max_size=400))
def test_any_config_file_content_is_a_config_or_one_config_error(
    tmp_path_factory: pytest.TempPathFactory, content: bytes
) -> None:
    path = tmp_path_factory.mktemp("cfg") / "platform.toml"
    path.write_bytes(content)
    try:
        load_config(PlatformConfig, path)
    except ConfigError as err:  # the one error the CLI prints as one message, no traceback
        assert str(err).startswith(f"{path}: ")


# --------------------------------------------------------------------------- ranges


def numeric_keys(cls: type) -> list[tuple[str, str, type]]:
    keys = []
    for section in dataclasses.fields(cls):
        section_type = typing.get_type_hints(cls)[section.name]
        hints = typing.get_type_hints(section_type)
        for item in dataclasses.fields(section_type):
            if hints[item.name] in (int, float):
                keys.append((section.name, item.name, hints[item.name]))
    return keys


@pytest.mark.parametrize(
    ("cls", "section", "key", "kind"),
    [(PlatformConfig, *k) for k in numeric_keys(PlatformConfig)]
    + [(StationConfig, *k) for k in numeric_keys(StationConfig)],
    ids=lambda value: value if isinstance(value, str) else None,
)
def test_every_numeric_key_has_a_range(cls: type, section: str, key: str, kind: type) -> None:
    """No key takes an absurd magnitude (1e308 s of reaction, 2**62 volts): each is bounded
    above and below, so nothing computed from it overflows."""
    item = next(f for f in dataclasses.fields(typing.get_type_hints(cls)[section]) if f.name == key)
    assert checks_of(item), f"{section}.{key} has no constraint"
    huge = "1e308" if kind is float else str(2**62)
    for value in (huge, f"-{huge}"):
        with pytest.raises(ConfigError, match=f"{section}.{key}"):
            load_config(cls, None, [f"{section}.{key}={value}"])


@settings(max_examples=200, deadline=None)
@given(
    reaction=st.floats(0, 1e308),
    distance=st.floats(0, 1e308),
    braking=st.floats(0, 1e308),
    latency=st.floats(0, 1e308),
)
def test_the_speed_cap_stops_within_the_distance_for_any_accepted_safety_config(
    reaction: float, distance: float, braking: float, latency: float
) -> None:
    overrides = [
        f"safety.reaction_s={reaction!r}",
        f"safety.stop_distance_m={distance!r}",
        f"safety.braking_mps2={braking!r}",
        f"safety.worst_latency_ms={latency!r}",
    ]
    try:
        config = load_config(PlatformConfig, None, overrides)
    except ConfigError:
        return
    assert_cap_stops_within_the_distance(config)


def assert_cap_stops_within_the_distance(config: PlatformConfig) -> None:
    """The cap without a latency report is a finite speed the robot stops from in time."""
    safety: SafetySection = config.safety
    cap = compute_cap(safety, config.platform.max_speed_kmh, None, None)
    assert math.isfinite(cap.cap_kmh)
    assert 0 <= cap.cap_kmh <= config.platform.max_speed_kmh
    speed = cap.cap_kmh / 3.6
    dead = safety.reaction_s + safety.worst_latency_ms / 1000
    stopping = dead * speed + speed * speed / (2 * safety.braking_mps2)
    assert stopping <= safety.stop_distance_m * (1 + 1e-9) + 1e-9


def test_reaction_1e308_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    code, err = platform_main(capsys, "--set", "safety.reaction_s=1e308", "config")
    assert code == 2
    assert err == ["brasidas-platform: safety.reaction_s: must be between 0 and 10, not 1e+308"]


def test_a_platform_id_a_beacon_cannot_carry_is_refused_at_the_door(
    capsys: pytest.CaptureFixture[str],
) -> None:
    code, err = platform_main(capsys, "--set", f"platform.id={'r' * 3000}", "config")
    assert code == 2
    assert len(err) == 1
    assert err[0].startswith("brasidas-platform: platform.id: must be 1-32 bytes of printable text")
    for bad in ("rover\n1", "rover\x1b[2J", "é" * 17):
        with pytest.raises(ConfigError, match="platform.id"):
            load_config(PlatformConfig, None, [f"platform.id={json.dumps(bad)}"])


def test_the_largest_beacon_is_checked_at_start_with_the_real_url() -> None:
    check_beacon_fits("r" * 32, "http://255.255.255.255:65535", os.urandom(32))
    with pytest.raises(ConfigError, match="platform.id: with signaling URL"):
        check_beacon_fits("r" * 32, f"http://{'h' * 60}.example:8765", os.urandom(32))


def test_the_station_refuses_a_key_file_others_can_read_too(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = key_file(tmp_path, 0o644)
    code = station_cli.main(["list", "--set", f"security.key_file={path}", "--wait", "0.1"])
    err = capsys.readouterr().err
    assert code == 2
    assert "permissions 0644 for the fleet key are too open" in err
    assert f"(chmod 600 {path})" in err


PLATFORM_KEYS = [
    (section.name, item.name)
    for section in dataclasses.fields(PlatformConfig)
    for item in dataclasses.fields(typing.get_type_hints(PlatformConfig)[section.name])
]
TOML_VALUES = st.one_of(
    st.floats(),
    st.integers(min_value=-(2**63), max_value=2**63 - 1),
    st.booleans(),
    st.text(max_size=50),
    st.lists(st.text(max_size=10), max_size=3),
)


def toml_value(value: object) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, float):
        return (
            "nan"
            if math.isnan(value)
            else ("inf" if value > 0 else "-inf")
            if math.isinf(value)
            else repr(value)
        )
    if isinstance(value, str):
        return json.dumps(value)
    if isinstance(value, list):
        return "[" + ", ".join(toml_value(item) for item in value) + "]"
    return str(value)


@settings(max_examples=300, deadline=None)
@given(entries=st.lists(st.tuples(st.sampled_from(PLATFORM_KEYS), TOML_VALUES), max_size=4))
def test_any_value_for_any_key_is_a_valid_config_or_one_config_error(
    tmp_path_factory: pytest.TempPathFactory, entries: list[tuple[tuple[str, str], object]]
) -> None:
    """Every key's type and range are checked at the door: whatever a config file sets, the
    result is a config whose speed cap is finite, or one ConfigError naming the file."""
    tables: dict[str, dict[str, object]] = {}
    for (section, key), value in entries:
        tables.setdefault(section, {})[key] = value
    text = "".join(
        f"[{section}]\n" + "".join(f"{key} = {toml_value(v)}\n" for key, v in keys.items())
        for section, keys in tables.items()
    )
    path = tmp_path_factory.mktemp("cfg") / "platform.toml"
    path.write_text(text)
    try:
        config = load_config(PlatformConfig, path)
    except ConfigError as err:
        assert str(err).startswith(f"{path}: ")
        return
    assert_cap_stops_within_the_distance(config)


@pytest.mark.parametrize(
    "key",
    [
        "signaling.heartbeat_interval",
        "beacon.min_interval",
        "velocity.deadman",
        "velocity.stats_interval",
        "failsafe.hold_after",
        "telemetry.rate_hz",
    ],
)
def test_a_period_or_rate_cannot_vanish(key: str) -> None:
    """A loop's period of 1e-300 s (stations told to send heartbeats that often, beacons at
    that rate) is a flood, not a setting."""
    with pytest.raises(ConfigError, match=key):
        load_config(PlatformConfig, None, [f"{key}=1e-300"])
