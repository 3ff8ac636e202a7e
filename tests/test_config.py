from __future__ import annotations

import tomllib
from pathlib import Path

import pytest

from brasidas.config import ConfigError, PlatformConfig, StationConfig, dump_toml, load_config
from platformd import cli as platform_cli


def test_dump_is_valid_toml_and_loads_back_to_the_same_config(tmp_path: Path) -> None:
    config = load_config(
        PlatformConfig, None, ["platform.id=rover-7", "beacon.destinations=['10.0.0.255']"]
    )
    text = dump_toml(config)
    assert tomllib.loads(text)["platform"]["id"] == "rover-7"
    path = tmp_path / "platform.toml"
    path.write_text(text)
    assert load_config(PlatformConfig, path) == config
    assert "# Platform id" in text  # documented defaults


def test_station_config_dumps_too() -> None:
    assert tomllib.loads(dump_toml(StationConfig()))["station"]["api_port"] == 8780


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[platform]\nnope = 1\n", "unknown key 'platform.nope'"),
        ("[nosuch]\nx = 1\n", "unknown section 'nosuch'"),
        ("[signaling]\nport = 'x'\n", "'signaling.port' must be an integer"),
        ("[signaling]\nport = true\n", "'signaling.port' must be an integer"),
        ("[beacon]\ndestinations = '1.2.3.4'\n", "'beacon.destinations' must be a list"),
        ("[security]\ninsecure = 1\n", "'security.insecure' must be true or false"),
        ("platform = 3\n", "'platform' must be a table"),
        ("[platform\n", "invalid TOML"),
    ],
)
def test_bad_files_name_file_and_key(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(PlatformConfig, path)
    assert str(err.value).startswith(str(path))
    assert message in str(err.value)


def test_missing_file() -> None:
    with pytest.raises(ConfigError, match="nowhere.toml: file not found"):
        load_config(PlatformConfig, "/nowhere.toml")


def test_overrides_parse_toml_values_or_bare_strings() -> None:
    config = load_config(
        PlatformConfig,
        None,
        [
            "signaling.port=9000",
            "telemetry.rate_hz=2",
            "platform.id=bare-word",
            "security.insecure=true",
        ],
    )
    assert config.signaling.port == 9000
    assert config.telemetry.rate_hz == 2.0 and isinstance(config.telemetry.rate_hz, float)
    assert config.platform.id == "bare-word"
    assert config.security.insecure is True
    with pytest.raises(ConfigError, match="expected SECTION.KEY=VALUE"):
        load_config(PlatformConfig, None, ["nonsense"])


def test_platform_cli_config_errors_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "p.toml"
    path.write_text("[motor]\nbaud = 9600\n")
    assert platform_cli.main(["--config", str(path), "config"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"brasidas-platform: {path}: unknown key 'motor.baud'"]


def test_platform_cli_prints_effective_config_with_sim(capsys: pytest.CaptureFixture[str]) -> None:
    assert platform_cli.main(["--sim", "--set", "platform.id=r2", "config"]) == 0
    printed = tomllib.loads(capsys.readouterr().out)
    assert printed["sim"]["enabled"] is True
    assert printed["platform"]["id"] == "r2"
    assert printed["signaling"]["port"] == 8765


def test_real_deployment_refuses_to_start_without_key(capsys: pytest.CaptureFixture[str]) -> None:
    assert platform_cli.main(["--set", "security.key_file=/nonexistent/fleet.key"]) == 2
    assert "fleet key not found" in capsys.readouterr().err
