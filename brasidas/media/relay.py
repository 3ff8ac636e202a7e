"""The payload camera: an RTSP H.264 camera forwarded to a station without re-encoding.

The seed's PiGstUDPThru. ``rtspsrc`` pulls the camera's RTP; the H.264 access units are
re-packetised (``rtph264depay ! rtph264pay config-interval=-1 mtu=1200``), never decoded, so
the station gets in-band SPS/PPS and packets that fit the mesh MTU, as from the NavCam; like
it, each station asking gets its own copy (``multiudpsink``, :mod:`brasidas.media.fanout`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from brasidas.media.fanout import Destinations, FanOutStream
from brasidas.media.gst import gst, link_all, make
from brasidas.media.video import PAYLOAD_TYPE

RTP_FORWARD_CAPS = (
    f"application/x-rtp,media=video,clock-rate=90000,encoding-name=H264,payload={PAYLOAD_TYPE}"
)


@dataclass
class ForwardSettings(Destinations):
    url: str = ""
    latency_ms: int = 50
    port: int = 5606
    mtu: int = 1200


class RtspForward(FanOutStream[ForwardSettings]):
    """RTSP (H.264) → RTP/UDP to each station asking, no decoding."""

    kind = "payload_camera"

    def describe(self) -> dict[str, Any]:
        return {
            **super().describe(),
            "codec": "H264",
            "source": self.settings.url,
            "rtp_caps": RTP_FORWARD_CAPS,
        }

    def explain(self, error: str) -> str:
        if error.startswith("source:"):
            return f"payload camera {self.settings.url}: {error.removeprefix('source:').strip()}"
        return error

    def build(self) -> Any:
        s = self.settings
        pipeline = gst().Pipeline.new(f"{self.name}-forward")
        source = make("rtspsrc", "source", location=s.url, latency=s.latency_ms)
        # Fail within seconds, not the default 20 s, when the camera is offline.
        source.set_property("tcp-timeout", 3_000_000)
        source.set_property("timeout", 3_000_000)
        depay = make("rtph264depay", "depay")
        chain = [
            depay,
            make("rtph264pay", config_interval=-1, mtu=s.mtu, pt=PAYLOAD_TYPE),
            self.make_sink(),
        ]
        pipeline.add(source)
        for element in chain:
            pipeline.add(element)
        link_all(*chain)
        source.connect("pad-added", _on_pad_added)
        return pipeline


def _on_pad_added(source: Any, pad: Any) -> None:
    """Streaming thread: link the camera's H.264 RTP pad; other media are left unlinked."""
    # Looked up by name: a Python reference here would outlive the pipeline's wrapper.
    parent = source.get_parent()
    depay = parent.get_by_name("depay") if parent is not None else None
    if depay is None:
        return
    current = pad.get_current_caps() or pad.query_caps(None)
    structure = current.get_structure(0) if current is not None else None
    if structure is None or structure.get_string("encoding-name") != "H264":
        return
    sink = depay.get_static_pad("sink")
    if not sink.is_linked():
        pad.link(sink)
