"""The suite's markers, given by what a test module uses, and its parallel workers' groups.

``browser``: drives headless Chromium (Playwright; the tests that use the ``browser``
fixture, the one way to it). ``netns``: builds network namespaces.
``interop``: talks to a real third-party client (MAVProxy, MAVSDK, the Foxglove client).
``slow``: any of those, or a module listed in :data:`SLOW_MODULES` (each of its tests waits
seconds of real time); ``make test-quick`` runs the rest. A test may also carry a marker
itself. A module found by what it imports marks its new tests too (no list to keep current).

Under pytest-xdist (``--dist loadgroup``) the browser tests run in :data:`BROWSER_LANES`
groups, each one test after another on one worker (so at most that many Chromiums draw at once:
four at once on two cores starved each other's page timing, while one lane alone was the
whole run's longest queue); a test that uses a fixture wider than one test (a module's network
or rig) runs in its module's group, on one worker, so the rig is built once; every other test
goes to whichever worker is free. The markers are registered in pyproject.toml.
"""

from __future__ import annotations

import functools
import os
import zlib
from pathlib import Path

import pytest

HINTS = {
    "browser": ("playwright",),
    "netns": ("requires_netns", "network_fixture"),
    "interop": ("mavproxy", "mavsdk", "foxglove_client"),
}
"""Words (lower case) in a module's source that give it the marker."""

SLOW_MODULES = frozenset(
    {
        "test_authority_takeover",
        "test_console_package",
        "test_demo",
        "test_failsafe",
        "test_hostile_process",
        "test_import_cycles",
        "test_leak_check",
        "test_loop_imports",
        "test_media",
        "test_media_audio",
        "test_media_station",
        "test_memory",
        "test_patrol_platform",
        "test_platform_process",
        "test_recorder",
        "test_teleop_reconnect",
    }
)
"""Modules whose tests each take seconds (``--durations`` of a whole run), beyond the ones
the hints mark."""

SLOW_TESTS = frozenset(
    {
        "test_autonomy_core.py::test_closed_route_driven_twice_passes_every_waypoint_and_avoids_the_keepout",
        "test_autonomy_core.py::test_rtk_receiver_patrol_stays_within_half_a_metre_of_the_path",
        "test_ax3500_sim.py::test_simulate_ax3500_standalone",
        "test_beacon.py::test_station_discovers_connects_by_id_and_forgets_a_silent_platform",
        "test_carmen.py::test_simulate_lidar_carmen_replays_a_log_on_a_pty",
        "test_config.py::test_platform_daemon_refuses_a_bad_value_before_starting_anything",
        "test_config.py::test_station_daemon_refuses_a_bad_value_before_starting_anything",
        "test_config_files.py::test_a_fifo_or_device_as_config_is_refused_at_once",
        "test_config_files.py::test_any_value_for_any_key_is_a_valid_config_or_one_config_error",
        "test_config_files.py::test_the_speed_cap_stops_within_the_distance_for_any_accepted_safety_config",
        "test_console_feed.py::test_access_units_reach_a_websocket_viewer_with_capture_times",
        "test_console_package.py::test_the_wheel_holds_every_console_file",
        "test_discovery_multicast.py::test_platforms_list_each_other_but_not_themselves",
        "test_gps.py::test_decoder_survives_any_bytes",
        "test_gps.py::test_valid_checksums_with_garbage_fields_never_raise",
        "test_hostile_signaling.py::test_a_local_websocket_that_never_reads_is_closed",
        "test_hostile_signaling.py::test_a_strangers_flood_at_full_rate_is_read_at_its_budget",
        "test_hostile_signaling.py::test_a_websocket_that_never_reads_is_closed",
        "test_hostile_signaling.py::test_half_sent_headers_are_closed_within_the_header_timeout",
        "test_hostile_signaling.py::test_idle_strangers_are_capped_and_a_station_still_connects",
        "test_imu.py::test_actor_turn_through_emulated_chip",
        "test_lidar.py::test_an_obstacle_becomes_a_keepout_the_patrol_plans_around_then_leaves",
        "test_lidar.py::test_hand_driving_is_slowed_then_stopped_short_of_an_obstacle",
        "test_lidar.py::test_patrol_stops_for_an_obstacle_the_map_does_not_have",
        "test_lidar_localization.py::test_a_gps_jump_is_refused_reported_and_raises_the_90_30_warning",
        "test_mapfiles_cli.py::test_big_files_up_to_the_limit_pass_the_station_and_bigger_are_refused",
        "test_mavlink_endpoint.py::test_a_ground_station_sees_a_rover_with_telemetry",
        "test_mavlink_endpoint.py::test_modes_start_and_stop_the_patrol",
        "test_media_audio_loss.py::test_lost_audio_packets_are_rebuilt_or_concealed",
        "test_media_fec_refresh.py::test_intra_refresh_has_no_keyframe_bursts",
        "test_media_keyframes.py::test_keyframe_interval_follows_live_framerate_changes",
        "test_platform_check.py::test_check_passes_on_the_simulators_and_names_wrong_and_missing_devices",
        "test_sdnotify.py::test_platform_process_says_ready_then_stopping_on_sigterm",
        "test_sim_gps.py::test_simulate_vehicle_standalone_moves_what_the_gps_reports",
        "test_source_ledger.py::test_every_path_is_charged_to_its_source_on_a_running_platform",
        "test_status_view.py::test_status_says_stale_when_the_gps_falls_silent",
        "test_telemetry_codec.py::test_any_snapshot_round_trips_within_the_size_limit",
        "test_teleop.py::test_drive_command_through_a_pty",
    }
)
"""Single tests of seconds each (3 s or more in a 2-worker ``--durations=0`` run; file::name,
parameters aside) in otherwise quick modules."""

BROWSER_LANES = max(1, int(os.environ.get("BROWSER_LANES", "1")))
"""Browser tests that may run at once (on as many workers; ``make test BROWSER_LANES=2``).
A test's lane follows from its name alone, so a new test moves no other test to another
lane. One: a 2-worker run's browser lane held 242 s of its 922 s of tests, a quarter, so at
four workers it ends with the others, and two Chromiums drawing at once on two cores starve
each other's page timing."""

SHARED_SCOPES = frozenset({"module", "package", "class"})


@functools.cache
def module_markers(path: Path) -> frozenset[str]:
    """The markers the module at ``path`` gets from what it uses."""
    source = path.read_text(encoding="utf-8").lower()
    found = {name for name, words in HINTS.items() if any(word in source for word in words)}
    if found or path.stem in SLOW_MODULES:
        found.add("slow")
    return frozenset(found)


SESSION_LOOP = pytest.mark.asyncio(loop_scope="session")
"""The loop of a test that uses the ``browser`` fixture: the worker's session loop, where its
one Playwright driver runs (a driver per test cost a Node start, 0.5-1.2 s, each)."""


def on_the_session_loop(item: pytest.Item) -> bool:
    """The test runs on the worker's session loop (its async fixtures must too)."""
    mark = item.get_closest_marker("asyncio")
    return mark is not None and mark.kwargs.get("loop_scope") == "session"


def shares_a_rig(item: pytest.Item) -> bool:
    """The test uses a fixture that outlives it (module, package or class scope)."""
    info = getattr(item, "_fixtureinfo", None)
    if info is None:
        return False
    return any(
        definitions[-1].scope in SHARED_SCOPES
        for definitions in info.name2fixturedefs.values()
        if definitions
    )


def apply(items: list[pytest.Item]) -> None:
    """Mark each collected test by its module, group the ones sharing a rig, and put the
    slow ones first (the browser tests, one worker's long queue, at the very front): the
    workers finish together instead of one starting a long queue near the end."""
    for item in items:
        path = Path(str(item.fspath))
        marks = module_markers(path)
        if "browser" in getattr(item, "fixturenames", ()):  # conftest's shared Chromium
            marks |= {"browser", "slow"}
            # First, so it is the mark pytest-asyncio reads (auto mode's plain one follows).
            item.add_marker(SESSION_LOOP, append=False)
        else:
            # Every Chromium is the ``browser`` fixture's: a test of a browser module without
            # it (a replay cache's quota, a codec) waits in no browser lane.
            marks -= {"browser"}
        for name in marks:
            item.add_marker(name)
        if f"{path.name}::{getattr(item, 'originalname', item.name)}" in SLOW_TESTS:
            item.add_marker("slow")
        if item.get_closest_marker("xdist_group") is not None:
            continue
        if "browser" in marks:
            item.add_marker(pytest.mark.xdist_group(browser_lane(path.name, item.name)))
        elif shares_a_rig(item):
            item.add_marker(pytest.mark.xdist_group(path.stem))
    items.sort(key=_start_order)


def browser_lane(module: str, test: str) -> str:
    """The xdist group of the browser test ``module::test``: one of :data:`BROWSER_LANES`."""
    return f"browser{zlib.crc32(f'{module}::{test}'.encode()) % BROWSER_LANES}"


def _start_order(item: pytest.Item) -> int:
    if item.get_closest_marker("browser") is not None:
        return 0
    return 1 if item.get_closest_marker("slow") is not None else 2
