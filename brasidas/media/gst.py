"""GStreamer access: initialisation, element creation with readable errors, capture stamps.

Everything that touches ``gi`` goes through here, so a machine without GStreamer gets one
clear :class:`MediaUnavailable` instead of an ImportError deep in a subsystem.
"""

from __future__ import annotations

import asyncio
import itertools
import threading
import time
from typing import Any

NTP_UNIX_OFFSET_NS = 2_208_988_800 * 1_000_000_000
"""Nanoseconds from the NTP epoch (1900) to the Unix epoch (1970)."""
NTP64_URI = "urn:ietf:params:rtp-hdrext:ntp-64"
"""RFC 6051 64-bit NTP header extension (capture time of each frame)."""
NTP64_EXT_ID = 1
"""The one-byte header extension id used for NTP-64 (``extmap-1`` in caps and SDP)."""
TWCC_URI = "http://www.ietf.org/id/draft-holmer-rmcat-transport-wide-cc-extensions-01"
"""Transport-wide sequence numbers: the receiver's rtpsession reports each packet's arrival
time (RTCP transport-cc feedback), the sender's reads a queue building from them."""
TWCC_EXT_ID = 2

# Debian package holding each element we may ask for, for the error message.
PACKAGES: dict[str, str] = {
    "x264enc": "gstreamer1.0-plugins-ugly",
    "openh264enc": "gstreamer1.0-plugins-bad",
    "v4l2h264enc": "gstreamer1.0-plugins-good (on a Raspberry Pi)",
    "omxh264enc": "gstreamer1.0-omx",
    "avdec_h264": "gstreamer1.0-libav",
    "clockoverlay": "gstreamer1.0-x",
    "timeoverlay": "gstreamer1.0-x",
    "rtphdrextntp64": "gstreamer1.0-plugins-good (1.22 or newer)",
    "opusenc": "gstreamer1.0-plugins-base",
    "opusdec": "gstreamer1.0-plugins-base",
    "rtspsrc": "gstreamer1.0-plugins-good",
    "v4l2src": "gstreamer1.0-plugins-good",
}


class MediaError(Exception):
    """A stream cannot be built or run; the message is the readable reason."""


class MediaUnavailable(MediaError):
    """GStreamer or its Python bindings are not installed."""


_lock = threading.Lock()
_gst: Any = None
_realtime_clock: Any = None


async def gst_off_the_loop() -> Any:
    """:func:`gst` from the event loop: the first call in a worker thread, so that importing
    and initialising GStreamer (0.19 s on a quiet machine) does not block the loop."""
    if _gst is not None:
        return _gst
    return await asyncio.to_thread(gst)


def gst() -> Any:
    """The initialised ``Gst`` module (imported and initialised once)."""
    global _gst
    if _gst is not None:
        return _gst
    with _lock:
        if _gst is None:
            try:
                import gi

                gi.require_version("Gst", "1.0")
                gi.require_version("GstRtp", "1.0")
                gi.require_version("GstVideo", "1.0")
                # GstRtp: the header extensions; GstVideo: force-key-unit events; Gio: the
                # streams' own sockets. All here, where an event loop makes the first call in
                # a thread (gst_off_the_loop): each import blocks what runs it.
                from gi.repository import (  # noqa: F401
                    Gio,
                    Gst,
                    GstRtp,
                    GstVideo,
                )
            except (ImportError, ValueError) as err:
                raise MediaUnavailable(
                    f"GStreamer Python bindings unavailable ({err}); run 'make deps'"
                ) from None
            Gst.init(None)
            _gst = Gst
    return _gst


def has_element(factory: str) -> bool:
    return gst().ElementFactory.find(factory) is not None


def make(factory: str, name: str | None = None, **props: Any) -> Any:
    """A new element with ``props`` set (``_`` for ``-``, ``async_`` for ``async``)."""
    element = gst().ElementFactory.make(factory, name)
    if element is None:
        package = PACKAGES.get(factory)
        hint = f" (install {package})" if package else ""
        raise MediaError(f"GStreamer element '{factory}' is not installed{hint}")
    for key, value in props.items():
        set_prop(element, key.rstrip("_").replace("_", "-"), value)
    return element


def set_prop(element: Any, key: str, value: Any) -> None:
    """Set a property; enums may be given by nick (``"zerolatency"``)."""
    if element.find_property(key) is None:
        raise MediaError(f"{element.get_factory().get_name()} has no property '{key}'")
    if isinstance(value, str) and not isinstance(element.get_property(key), str):
        gst().util_set_object_arg(element, key, value)
        current = element.get_property(key)
        nick = getattr(current, "value_nick", None)
        if nick is not None and value not in (nick, getattr(current, "value_name", None)):
            # util_set_object_arg only logs a bad nick; a typo in config must be an error.
            raise MediaError(f"{element.get_factory().get_name()}: invalid {key} '{value}'")
    else:
        element.set_property(key, value)


def caps(text: str) -> Any:
    result = gst().Caps.from_string(text)
    if result is None:
        raise MediaError(f"invalid caps: {text}")
    return result


def link_all(*elements: Any) -> None:
    """Link elements in order; MediaError names the pair that will not link."""
    for upstream, downstream in itertools.pairwise(elements):
        if not upstream.link(downstream):
            raise MediaError(
                f"cannot link {upstream.get_name()} to {downstream.get_name()} "
                "(caps do not negotiate)"
            )


def realtime_clock() -> Any:
    """A system clock on CLOCK_REALTIME: base time + PTS is then the wall-clock capture time."""
    global _realtime_clock
    if _realtime_clock is None:
        from gi.repository import GObject

        Gst = gst()
        _realtime_clock = GObject.new(Gst.SystemClock, clock_type=Gst.ClockType.REALTIME)
    return _realtime_clock


def ntp_caps() -> Any:
    return caps("timestamp/x-ntp")


def stamp_capture_time(identity: Any, buffer: Any, reference: Any) -> None:
    """``identity`` handoff (streaming thread): attach the frame's capture time as NTP meta.

    The pipeline runs on :func:`realtime_clock`, so base time + PTS is the Unix time at which
    the source captured the frame; rtphdrextntp64 writes that meta into every packet.
    """
    pts = buffer.pts
    if pts == gst().CLOCK_TIME_NONE:
        return
    buffer.add_reference_timestamp_meta(
        reference, identity.get_base_time() + pts + NTP_UNIX_OFFSET_NS, gst().CLOCK_TIME_NONE
    )


def capture_age_ms(buffer: Any, reference: Any) -> float | None:
    """Milliseconds since the capture time the buffer carries (NTP meta), or None."""
    meta = buffer.get_reference_timestamp_meta(reference)
    if meta is None or meta.timestamp == 0:
        return None
    captured_ns: int = meta.timestamp
    return (time.time_ns() + NTP_UNIX_OFFSET_NS - captured_ns) / 1e6
