"""The admission section both daemons share, and the old key names operators' files still use
(``signaling.*`` on the platform, ``station.api_*`` on the station): read as the new keys,
with one line saying so at start-up and in ``brasidas-platform config``."""

from __future__ import annotations

import dataclasses
import logging
import tomllib
from pathlib import Path

import pytest

import platformd.cli as platform_cli
from brasidas.admission import admission_limits
from brasidas.config import ConfigError, PlatformConfig, StationConfig, dump_toml, load_config
from brasidas.config.admission import AdmissionSection, StrangerAdmissionSection

OLD_PLATFORM_FILE = """\
[signaling]
port = 8765
max_connections = 300
max_strangers = 32
max_strangers_per_host = 4
header_timeout = 2.5
body_timeout = 3.5
idle_timeout = 20.0
write_timeout = 7.0
max_unsent_bytes = 131072
reserved_fds = 64
stranger_bytes_per_s = 8192
max_batch = 50
"""
"""A platform file written before the admission section: every admission key, old names."""

OLD_STATION_FILE = """\
[station]
id = "base"
api_max_connections = 100
api_header_timeout = 2.5
api_body_timeout = 3.5
api_idle_timeout = 90.0
api_write_timeout = 7.0
api_max_unsent_bytes = 131072
api_reserved_fds = 64
api_max_batch = 50
"""


def test_both_daemons_share_one_admission_section() -> None:
    platform, station = PlatformConfig().admission, StationConfig().admission
    assert type(station) is AdmissionSection
    assert isinstance(platform, AdmissionSection)
    assert isinstance(platform, StrangerAdmissionSection)
    common = {item.name for item in dataclasses.fields(AdmissionSection)}
    assert common <= {item.name for item in dataclasses.fields(platform)}
    # The station keeps its own defaults for the shared keys.
    assert (station.max_connections, station.idle_timeout) == (256, 60.0)
    assert station.max_unsent_bytes == 4 << 20
    assert (platform.max_connections, platform.idle_timeout) == (512, 15.0)
    assert platform.max_unsent_bytes == 1 << 20
    # A server without sessions trusts every connection; signaling holds strangers to caps.
    assert admission_limits(station).trusted
    assert not admission_limits(platform).trusted
    assert admission_limits(platform).max_strangers_per_host == 8


def test_an_old_platform_file_reads_as_the_new_keys(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "platform.toml"
    path.write_text(OLD_PLATFORM_FILE)
    notices: list[str] = []
    with caplog.at_level(logging.WARNING, "brasidas.config.loader"):
        config = load_config(PlatformConfig, path, (), notices)
    assert config.admission == StrangerAdmissionSection(
        max_connections=300,
        max_strangers=32,
        max_strangers_per_host=4,
        header_timeout=2.5,
        body_timeout=3.5,
        idle_timeout=20.0,
        write_timeout=7.0,
        max_unsent_bytes=131072,
        reserved_fds=64,
        stranger_bytes_per_s=8192,
        max_batch=50,
    )
    assert config.signaling.port == 8765
    assert len(notices) == 11
    assert notices[0] == (
        f"deprecated key signaling.max_connections in {path}: it is now "
        "admission.max_connections (read as such); rename it"
    )
    assert [record.getMessage() for record in caplog.records] == notices
    limits = admission_limits(config.admission)
    assert (limits.max_connections, limits.max_strangers, limits.header_timeout) == (300, 32, 2.5)


def test_an_old_station_file_reads_as_the_new_keys(tmp_path: Path) -> None:
    path = tmp_path / "station.toml"
    path.write_text(OLD_STATION_FILE)
    notices: list[str] = []
    config = load_config(StationConfig, path, (), notices)
    assert config.admission == AdmissionSection(
        max_connections=100,
        header_timeout=2.5,
        body_timeout=3.5,
        idle_timeout=90.0,
        write_timeout=7.0,
        max_unsent_bytes=131072,
        reserved_fds=64,
        max_batch=50,
    )
    assert config.station.id == "base"
    assert len(notices) == 8
    assert "station.api_idle_timeout" in notices[3]
    assert "admission.idle_timeout" in notices[3]


def test_the_new_names_give_no_notice_and_old_ones_on_the_command_line_do() -> None:
    notices: list[str] = []
    config = load_config(PlatformConfig, None, ["admission.max_strangers=16"], notices)
    assert config.admission.max_strangers == 16
    assert notices == []
    station = load_config(StationConfig, None, ["station.api_write_timeout=2"], notices)
    assert station.admission.write_timeout == 2.0
    assert notices == [
        "deprecated key station.api_write_timeout on the command line: it is now "
        "admission.write_timeout (read as such); rename it"
    ]


def test_an_old_name_is_checked_as_the_new_key() -> None:
    with pytest.raises(ConfigError, match=r"^admission\.max_strangers: must be >= "):
        load_config(PlatformConfig, None, ["signaling.max_strangers_per_host=100"])
    with pytest.raises(ConfigError, match=r"^admission\.max_batch: must be between 1 and"):
        load_config(StationConfig, None, ["station.api_max_batch=0"])


def test_both_names_in_one_file_is_an_error_and_a_later_source_wins(tmp_path: Path) -> None:
    path = tmp_path / "platform.toml"
    path.write_text("[signaling]\nmax_batch = 10\n[admission]\nmax_batch = 20\n")
    with pytest.raises(ConfigError) as raised:
        load_config(PlatformConfig, path)
    assert str(raised.value) == (
        f"{path}: signaling.max_batch: renamed admission.max_batch, which is also set: "
        "keep only admission.max_batch"
    )
    path.write_text("[signaling]\nmax_batch = 10\n")
    assert load_config(PlatformConfig, path, ["admission.max_batch=30"]).admission.max_batch == 30


def test_platform_config_prints_the_notice_above_the_config(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "platform.toml"
    path.write_text("[signaling]\nidle_timeout = 30.0\n")
    assert platform_cli.main(["--config", str(path), "config"]) == 0
    out = capsys.readouterr().out
    first = out.splitlines()[0]
    assert first == (
        f"# deprecated key signaling.idle_timeout in {path}: it is now admission.idle_timeout "
        "(read as such); rename it"
    )
    printed = tomllib.loads(out)
    assert printed["admission"]["idle_timeout"] == 30.0
    assert "idle_timeout" not in printed["signaling"]


def test_the_dump_documents_the_shared_keys_for_both_daemons() -> None:
    for config in (PlatformConfig(), StationConfig()):
        admission = dump_toml(config).split("[admission]\n", 1)[1].split("\n[", 1)[0]
        assert "# A request's headers must arrive within this (s)" in admission
        assert "header_timeout = 5.0" in admission
    assert "max_strangers = 64" in dump_toml(PlatformConfig())
    assert "max_strangers" not in dump_toml(StationConfig())
