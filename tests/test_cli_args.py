"""Command-line options work before or after the command name."""

from __future__ import annotations

from stationd.cli import build_parser, parse_args


def test_station_options_before_and_after_the_command_name() -> None:
    parser = build_parser()
    before = parser.parse_args(["--set", "station.api_port=1", "--json", "status", "rover"])
    assert before.overrides == ["station.api_port=1"]
    assert before.json is True
    after = parser.parse_args(["status", "rover", "--set", "station.api_port=2", "--json"])
    assert after.command_overrides == ["station.api_port=2"]
    assert after.json is True
    both = parser.parse_args(["--set", "a.b=1", "list", "--set", "c.d=2"])
    assert (both.overrides, both.command_overrides) == (["a.b=1"], ["c.d=2"])
    assert both.json is False
    assert both.config is None


def test_southern_and_western_coordinates_are_waypoints_not_options() -> None:
    for argv in (
        ["route", "rover", "-36.88,174.82", "-36.881,-174.8"],
        ["route", "rover", "--json", "--", "-36.88,174.82", "-36.881,-174.8"],
        ["--json", "route", "rover", "-36.88,174.82", "-36.881,-174.8", "--skip-unsupported"],
    ):
        args = parse_args(argv)
        assert [w.strip() for w in args.waypoints] == ["-36.88,174.82", "-36.881,-174.8"], argv
    assert parse_args(["route", "rover", "-36.88, 174.82"]).waypoints == [" -36.88, 174.82"]
