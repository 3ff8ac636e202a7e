"""Media policy without GStreamer: framerate by mode, 10.1 payloads, hosts, SDP."""

from __future__ import annotations

import pytest

from brasidas.codecs.commands import PayloadError
from brasidas.config import NavCamSection
from brasidas.media.navcam import FrameratePolicy, navcam_settings, parse_framerate
from brasidas.media.video import VideoSettings
from platformd.media import check_host, host_from_payload
from stationd.media import receive_host, sdp_text


def test_framerate_follows_the_override_and_10_5_sets_the_current_mode() -> None:
    policy = FrameratePolicy(engaged_fps=30, idle_fps=5, limit=30)
    assert policy.current == 5
    assert policy.set_override(True) == 30
    assert policy.set_current("15") == 15
    assert policy.set_override(False) == 5  # the idle rate was not touched
    assert policy.set_override(True) == 15
    for raw, reason in (("0", "1-30"), ("1000", "1-30"), ("fast", "integer"), ("", "integer")):
        with pytest.raises(ValueError, match=reason):
            policy.set_current(raw)
    assert policy.current == 15


def test_configured_rates_are_clamped_to_the_camera() -> None:
    policy = FrameratePolicy(engaged_fps=60, idle_fps=0, limit=30)
    assert policy.rates == {"engaged": 30, "idle": 1}
    assert parse_framerate(" 7 ", 30) == 7


def test_navcam_settings_from_config() -> None:
    settings = navcam_settings(NavCamSection(format="mjpeg", encoder="x264enc"), sim=True)
    assert (settings.width, settings.height, settings.camera_framerate) == (640, 480, 30)
    assert settings.framerate == 5
    assert settings.test_source
    assert settings.source_format == "mjpeg"


def test_bitrate_scales_with_the_framerate() -> None:
    settings = VideoSettings(bitrate_kbps=1500, camera_framerate=30, framerate=30)
    assert settings.effective_bitrate_kbps() == 1500
    settings.framerate = 5
    assert settings.effective_bitrate_kbps() == 250
    settings.framerate = 1
    assert settings.effective_bitrate_kbps() == 150  # floor: a still picture stays legible


@pytest.mark.parametrize(
    ("payload", "default", "host"),
    [
        ("host=10.0.0.2", "", "10.0.0.2"),
        ("10.0.0.3", "", "10.0.0.3"),
        (" host = station.mesh ", "", "station.mesh"),
        ("", "127.0.0.1", "127.0.0.1"),
        ("host=::1", "", "::1"),
    ],
)
def test_start_payload_hosts(payload: str, default: str, host: str) -> None:
    assert host_from_payload(payload, default) == host


@pytest.mark.parametrize("payload", ["", "host=", "host=bad host", "host=a..b", "x=1,y=2"])
def test_bad_start_payloads_are_rejected(payload: str) -> None:
    with pytest.raises(PayloadError):
        host_from_payload(payload)


def test_check_host() -> None:
    assert check_host(" 192.168.1.5 ") == "192.168.1.5"
    with pytest.raises(PayloadError, match="not an IP address"):
        check_host("-bad")


def test_sdp_describes_the_stream() -> None:
    text = sdp_text(5600, listen_host="127.0.0.1", name="rover nav", platform_host="10.0.0.9")
    lines = text.split("\r\n")
    assert lines[0] == "v=0"
    assert text.endswith("\r\n")
    assert "c=IN IP4 127.0.0.1" in lines
    assert "m=video 5600 RTP/AVP 96" in lines
    assert "a=rtpmap:96 H264/90000" in lines
    assert "o=- 0 0 IN IP4 10.0.0.9" in lines
    assert "a=extmap:1 urn:ietf:params:rtp-hdrext:ntp-64" in lines
    assert "c=IN IP6 ::1" in sdp_text(5600, listen_host="::1")


def test_receive_host_is_loopback_only_for_a_loopback_platform() -> None:
    assert receive_host("127.0.0.1") == "127.0.0.1"
    assert receive_host("localhost") == "127.0.0.1"
    assert receive_host("10.144.0.11") == "0.0.0.0"
