"""Configuration: loading, every key validated at the door, frozen after, and the CLIs' refusal."""

from __future__ import annotations

import asyncio
import dataclasses
import sys
import tomllib
from pathlib import Path

import pytest

from brasidas.config import (
    ConfigError,
    PlatformConfig,
    StationConfig,
    dump_toml,
    load_config,
)
from brasidas.config.loader import checks_of
from platformd import cli as platform_cli
from stationd import cli as station_cli


def test_dump_is_valid_toml_and_loads_back_to_the_same_config(tmp_path: Path) -> None:
    config = load_config(
        PlatformConfig, None, ["platform.id=rover-7", "beacon.destinations=['10.0.0.255']"]
    )
    assert config.beacon.destinations == ("10.0.0.255",)
    text = dump_toml(config)
    assert tomllib.loads(text)["platform"]["id"] == "rover-7"
    path = tmp_path / "platform.toml"
    path.write_text(text)
    assert load_config(PlatformConfig, path) == config
    assert "# Platform id" in text  # documented defaults


def test_dump_prints_each_keys_constraints_as_comments() -> None:
    lines = dump_toml(PlatformConfig()).splitlines()
    rate = lines.index("rate_hz = 100.0")  # imu's
    assert lines[rate - 1] == "# Must be between 4 and 1000."
    assert '# Must be one of "N", "E", "O", "M", "S".' in lines
    assert "# max_interval must be > beacon.min_interval (0.6)." in lines
    station = dump_toml(StationConfig()).splitlines()
    assert station[station.index("rate_hz = 20.0") - 1] == "# Must be between 1 and 100."


def test_station_config_dumps_too() -> None:
    assert tomllib.loads(dump_toml(StationConfig()))["station"]["api_port"] == 8780


def test_defaults_are_valid() -> None:
    assert load_config(PlatformConfig) == PlatformConfig()
    assert load_config(StationConfig) == StationConfig()


def test_every_constrained_key_declares_a_rule_a_default_meets() -> None:
    checked = 0
    for config in (PlatformConfig(), StationConfig()):
        for section in dataclasses.fields(config):
            value = getattr(config, section.name)
            for item in dataclasses.fields(value):
                for check in checks_of(item):
                    assert check.ok(getattr(value, item.name)), (section.name, item.name)
                    checked += 1
    assert checked > 80


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[platform]\nnope = 1\n", "platform.nope: unknown key"),
        ("[motor]\nbaud = 9600\n", "motor.baud: unknown key (did you mean 'baudrate'?)"),
        ("[nosuch]\nx = 1\n", "nosuch: unknown section"),
        ("[signaling]\nport = 'x'\n", "signaling.port: must be an integer, not 'x'"),
        ("[signaling]\nport = true\n", "signaling.port: must be an integer"),
        ("[signaling]\nport = 70000\n", "signaling.port: must be a port number (0-65535"),
        ("[beacon]\ndestinations = '1.2.3.4'\n", "beacon.destinations: must be a list"),
        ("[security]\ninsecure = 1\n", "security.insecure: must be true or false"),
        ("[imu]\nrate_hz = 0\n", "imu.rate_hz: must be between 4 and 1000, not 0.0"),
        ("[imu]\nrate_hz = nan\n", "imu.rate_hz: must be a finite number"),
        (
            "[beacon]\nmin_interval = 5\n",
            "beacon.max_interval: must be > beacon.min_interval (5.0)",
        ),
        ("platform = 3\n", "platform: must be a table"),
        ("[platform\n", "invalid TOML"),
    ],
)
def test_bad_files_name_file_and_key(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as err:
        load_config(PlatformConfig, path)
    assert str(err.value).startswith(f"{path}: ")
    assert message in str(err.value)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("imu.rate_hz=0", "imu.rate_hz: must be between 4 and 1000, not 0.0"),
        ("imu.rate_hz=inf", "imu.rate_hz: must be a finite number, not inf"),
        ("imu.address=0x70", "imu.address: must be one of 104, 105, not 112"),
        ("imu.accel_range_g=3", "imu.accel_range_g: must be one of 2, 4, 8, 16, not 3"),
        ("telemetry.rate_hz=0", "telemetry.rate_hz: must be between 0.1 and 50, not 0.0"),
        ("signaling.port=-1", "signaling.port: must be a port number (0-65535; 0: any free"),
        ("signaling.host=rover.local", 'signaling.host: must be an IP address, not "rover.local"'),
        ("signaling.advertise_host=bad_name!", "signaling.advertise_host: must be empty or"),
        ("signaling.session_timeout=0", "signaling.session_timeout: must be > 0 and <= 3600"),
        ("beacon.port=0", "beacon.port: must be a port number (1-65535), not 0"),
        ("beacon.destinations=[]", "beacon.destinations: must be non-empty"),
        ("beacon.destinations=['10.0.0.300']", "beacon.destinations: must be a list of items"),
        ("beacon.min_interval=5", "beacon.max_interval: must be > beacon.min_interval (5.0)"),
        ("motor.parity=X", 'motor.parity: must be one of "N", "E", "O", "M", "S", not "X"'),
        ("motor.bytesize=9", "motor.bytesize: must be one of 5, 6, 7, 8, not 9"),
        (
            "sim.gps_receiver=zedf9p",
            'sim.gps_receiver: must be one of "neo6m", "rtk", not "zedf9p"',
        ),
        ("motor.baudrate=9601", "motor.baudrate: must be one of 1200,"),
        ("motor.refresh_hz=1", "motor.refresh_hz: must be between 2 and 50, not 1.0"),
        ("motor.linear_scale=1.5", "motor.linear_scale: must be > 0 and <= 1, not 1.5"),
        ("motor.main_lights_output=CD", "motor.main_lights_output: must be empty, one control"),
        ("motor.port=''", "motor.port: must be non-empty"),
        ("velocity.deadman=0", "velocity.deadman: must be between 0.02 and 10, not 0.0"),
        ("gps.sim_rate_hz=11", "gps.sim_rate_hz: must be between 1 and 10, not 11.0"),
        ("navcam.framerate=31", "navcam.framerate: must be between 1 and 30, not 31"),
        ("navcam.idle_framerate=0", "navcam.idle_framerate: must be between 1 and 30, not 0"),
        ("navcam.format=h264", 'navcam.format: must be one of "raw", "mjpeg", not "h264"'),
        ("navcam.encoder=nvenc", "navcam.encoder: must be one of"),
        ("navcam.sim_pattern=plaid", "navcam.sim_pattern: must be one of"),
        ("payload_camera.enabled=true", "payload_camera.url: must be an rtsp URL when enabled"),
        ("payload_camera.url=http://cam/x", "payload_camera.url: must be empty or a rtsp/rtsps"),
        ("sim.latitude=91", "sim.latitude: must be between -90 and 90, not 91.0"),
        ("telemetry.battery_high_v=22", "telemetry.battery_high_v: must be > telemetry.battery"),
    ],
)
def test_platform_values_out_of_range_name_the_key(override: str, message: str) -> None:
    with pytest.raises(ConfigError) as err:
        load_config(PlatformConfig, None, [override])
    assert str(err.value).startswith(message)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    ("override", "message"),
    [
        ("teleop.rate_hz=0", "teleop.rate_hz: must be between 1 and 100, not 0.0"),
        ("teleop.drive_timeout=0", "teleop.drive_timeout: must be > 0"),
        ("station.api_port=65536", "station.api_port: must be a port number"),
        ("station.api_host=localhost", "station.api_host: must be an IP address"),
        ("discovery.expiry=-1", "discovery.expiry: must be > 0"),
        ("joystick.deadzone=1", "joystick.deadzone: must be between 0 and 0.9, not 1.0"),
        ("joystick.angular_axis=1", "joystick.angular_axis: must be another axis than linear"),
        ("telemetry.loss_window=0", "telemetry.loss_window: must be between 1 and 10000, not 0"),
        ("telemetry.battery_clear_v=22", "telemetry.battery_clear_v: must be >= telemetry.batt"),
        ("telemetry.controller_clear_c=75", "telemetry.controller_clear_c: must be <= telemetr"),
    ],
)
def test_station_values_out_of_range_name_the_key(override: str, message: str) -> None:
    with pytest.raises(ConfigError) as err:
        load_config(StationConfig, None, [override])
    assert str(err.value).startswith(message)


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
    assert config.telemetry.rate_hz == 2.0
    assert isinstance(config.telemetry.rate_hz, float)
    assert config.platform.id == "bare-word"
    assert config.security.insecure is True
    with pytest.raises(ConfigError, match="expected SECTION.KEY=VALUE"):
        load_config(PlatformConfig, None, ["nonsense"])


def test_a_later_value_wins_and_is_what_gets_checked(tmp_path: Path) -> None:
    path = tmp_path / "p.toml"
    path.write_text("[imu]\nrate_hz = 0\n")
    assert load_config(PlatformConfig, path, ["imu.rate_hz=50"]).imu.rate_hz == 50.0
    with pytest.raises(ConfigError, match=r"^imu\.rate_hz: must be between 4 and 1000"):
        load_config(PlatformConfig, None, ["imu.rate_hz=50", "imu.rate_hz=0"])


def test_a_loaded_config_is_frozen() -> None:
    config = load_config(PlatformConfig)
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.imu.rate_hz = 0.0  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        config.sim = config.sim  # type: ignore[misc]
    station = load_config(StationConfig)
    with pytest.raises(dataclasses.FrozenInstanceError):
        station.station.api_port = 0  # type: ignore[misc]


def test_sim_and_insecure_flags_are_applied_while_loading() -> None:
    args = platform_cli.build_parser().parse_args(["--sim", "--insecure"])
    config = platform_cli.load_platform_config(args)
    assert config.sim.enabled
    assert config.security.insecure


# --------------------------------------------------------------------------- the CLIs


def test_platform_cli_config_errors_exit_2(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "p.toml"
    path.write_text("[imu]\nrate_hz = 0\n")
    assert platform_cli.main(["--config", str(path), "config"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"brasidas-platform: {path}: imu.rate_hz: must be between 4 and 1000, not 0.0"]


def test_platform_cli_prints_effective_config_with_sim(capsys: pytest.CaptureFixture[str]) -> None:
    assert platform_cli.main(["--sim", "--set", "platform.id=r2", "config"]) == 0
    printed = tomllib.loads(capsys.readouterr().out)
    assert printed["sim"]["enabled"] is True
    assert printed["platform"]["id"] == "r2"
    assert printed["signaling"]["port"] == 8765


def test_real_deployment_refuses_to_start_without_key(capsys: pytest.CaptureFixture[str]) -> None:
    assert platform_cli.main(["--set", "security.key_file=/nonexistent/fleet.key"]) == 2
    assert "fleet key not found" in capsys.readouterr().err


async def run_process(*argv: str) -> tuple[int, str, str]:
    process = await asyncio.create_subprocess_exec(
        sys.executable,
        *argv,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    out, err = await asyncio.wait_for(process.communicate(), 60)
    assert process.returncode is not None
    return process.returncode, out.decode(), err.decode()


async def test_platform_daemon_refuses_a_bad_value_before_starting_anything() -> None:
    """Defect 6: ``imu.rate_hz=0`` crash-restarted the IMU actor forever; now the daemon
    refuses it with one line and exits 2 before any subsystem (the simulators included)."""
    code, out, err = await run_process(
        "-m", "platformd", "--sim", "--set", "signaling.port=0", "--set", "imu.rate_hz=0"
    )
    assert (code, out) == (2, "")
    assert err.splitlines() == [
        "brasidas-platform: imu.rate_hz: must be between 4 and 1000, not 0.0"
    ]


async def test_station_daemon_refuses_a_bad_value_before_starting_anything() -> None:
    code, out, err = await run_process(
        "-m", "stationd", "serve", "--set", "station.api_port=0", "--set", "teleop.rate_hz=0"
    )
    assert (code, out) == (2, "")
    assert err.splitlines() == [
        "brasidas-station: teleop.rate_hz: must be between 1 and 100, not 0.0"
    ]


def test_every_station_command_refuses_a_bad_value(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "station.toml"
    path.write_text("[teleop]\nrate_hz = 0\n")
    for argv in (["list"], ["status", "rover"], ["keygen"], ["serve"]):
        assert station_cli.main([*argv, "--config", str(path)]) == 2, argv
        err = capsys.readouterr().err.strip().splitlines()
        assert err == [
            f"brasidas-station: {path}: teleop.rate_hz: must be between 1 and 100, not 0.0"
        ]


def test_a_bad_log_level_is_refused(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        platform_cli.main(["--log-level", "LOUD", "config"])
    assert exit_.value.code == 2
    assert "'LOUD' is not one of DEBUG, INFO" in capsys.readouterr().err


def test_a_session_timeout_that_would_pre_empt_the_failsafe_ladder_is_refused() -> None:
    with pytest.raises(ConfigError) as err:
        load_config(PlatformConfig, None, ["signaling.session_timeout=1.5"])
    assert str(err.value).startswith(
        "signaling.session_timeout: must be > failsafe.hold_after (1.5): a silent override "
        "holder's session would end before the failsafe ladder holds, not 1.5"
    )
    load_config(PlatformConfig, None, ["signaling.session_timeout=1.5", "failsafe.hold_after=1"])
