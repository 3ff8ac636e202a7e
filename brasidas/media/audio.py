"""Opus over RTP: a microphone out (the seed's PiGstAudioOut) and a speaker in (PiGstAudioIn).

Out: ALSA capture (or ``audiotestsrc`` in sim and tests) → 48 kHz mono → ``opusenc`` (20 ms
frames, low-delay, in-band FEC) → ``rtpopuspay`` → ``multiudpsink sync=false``, one destination per station
(:mod:`brasidas.media.fanout`). In: ``udpsrc`` with explicit caps
→ a small jitter buffer → ``rtpopusdepay`` → ``opusdec`` (in-band FEC, loss concealment) → S16 → ALSA playback (or
``fakesink``), with the peak level of what was received, so a test can tell sound from silence.
"""

from __future__ import annotations

import weakref
from array import array
from dataclasses import dataclass
from typing import Any

from brasidas.media.fanout import Destinations, FanOutStream
from brasidas.media.gst import caps, gst, link_all, make
from brasidas.media.pipeline import PipelineStream

FEC_EXPECTED_LOSS_PCT = 10
"""The loss the Opus encoder plans its FEC for (a mesh loses 1-10 %)."""

AUDIO_PAYLOAD_TYPE = 97
RTP_AUDIO_CAPS = (
    "application/x-rtp,media=audio,clock-rate=48000,encoding-name=OPUS,"
    f"payload={AUDIO_PAYLOAD_TYPE}"
)
SILENCE_PEAK = 64
"""A 16-bit peak at or below this is silence (about -54 dBFS)."""


@dataclass
class AudioSettings(Destinations):
    device: str = ""
    """ALSA device (``hw:1,0``); empty: the system default."""
    test_source: bool = False
    """A 440 Hz test tone instead of the microphone (sim, tests)."""
    bitrate: int = 24000
    port: int = 5602


class AudioOut(FanOutStream[AudioSettings]):
    """Microphone → Opus → RTP/UDP to each station asking."""

    kind = "audio_out"

    def describe(self) -> dict[str, Any]:
        return {
            **super().describe(),
            "codec": "OPUS",
            "bitrate": self.settings.bitrate,
            "rtp_caps": RTP_AUDIO_CAPS,
        }

    def build(self) -> Any:
        s = self.settings
        pipeline = gst().Pipeline.new(f"{self.name}-out")
        if s.test_source:
            source = make("audiotestsrc", "source", is_live=True, freq=440.0, volume=0.3)
        elif s.device:
            source = make("alsasrc", "source", device=s.device)
        else:
            source = make("autoaudiosrc", "source")
        chain = [
            source,
            make("audioconvert"),
            make("audioresample"),
            make("capsfilter", caps=caps("audio/x-raw,rate=48000,channels=1")),
            make(
                "opusenc",
                bitrate=s.bitrate,
                frame_size=20,
                audio_type="restricted-lowdelay",
                # In-band FEC: each packet carries a low-rate copy of the one before, so a
                # single lost packet is rebuilt by the receiver (issue 28).
                inband_fec=True,
                packet_loss_percentage=FEC_EXPECTED_LOSS_PCT,
            ),
            make("rtpopuspay", pt=AUDIO_PAYLOAD_TYPE),
            self.make_sink(),
        ]
        for element in chain:
            pipeline.add(element)
        link_all(*chain)
        return pipeline


class AudioIn(PipelineStream):
    """RTP/UDP Opus → speaker, measuring the received peak level."""

    kind = "audio_in"

    def __init__(
        self,
        name: str,
        *,
        port: int,
        host: str = "127.0.0.1",
        device: str = "",
        sink: str = "",
        jitter_ms: int = 40,
        conceal: bool = True,
        **kwargs: Any,
    ) -> None:
        super().__init__(name, **kwargs)
        self.conceal = conceal
        """Rebuild lost packets from in-band FEC, else conceal them (PLC)."""
        self.host = host
        self.port = port
        self.device = device
        self.sink_factory = sink or ("alsasink" if device else "autoaudiosink")
        self.jitter_ms = jitter_ms
        self.buffers = 0
        self.samples = 0
        """Samples decoded (48 kHz): the sound's duration, concealed losses included."""
        self.loud_buffers = 0
        self.peak = 0
        """Highest 16-bit sample magnitude received so far."""

    def destination(self) -> str:
        return f"{self.host}:{self.port}"

    def describe(self) -> dict[str, Any]:
        return {
            **super().describe(),
            "codec": "OPUS",
            "rtp_caps": RTP_AUDIO_CAPS,
            "host": self.host,
            "port": self.port,
            "buffers": self.buffers,
            "peak": self.peak,
        }

    @property
    def hears_sound(self) -> bool:
        return self.loud_buffers > 0

    def build(self) -> Any:
        Gst = gst()
        pipeline = Gst.Pipeline.new(f"{self.name}-in")
        sink = make(self.sink_factory, "sink")
        if self.device and sink.find_property("device") is not None:
            sink.set_property("device", self.device)
        if sink.find_property("sync") is not None and self.sink_factory == "fakesink":
            sink.set_property("sync", False)
        # A lost packet: rebuilt from the next one's FEC, else concealed (PLC) from the
        # jitter buffer's lost-packet event, so the sound stutters instead of dropping out.
        decoder = make("opusdec", plc=self.conceal, use_inband_fec=self.conceal)
        s16 = make("capsfilter", caps=caps("audio/x-raw,format=S16LE,channels=1"))
        chain = [
            make("udpsrc", "source", address=self.host, port=self.port, caps=caps(RTP_AUDIO_CAPS)),
            make(
                "rtpjitterbuffer",
                latency=self.jitter_ms,
                drop_on_latency=True,
                do_lost=self.conceal,
            ),
            make("rtpopusdepay"),
            decoder,
            make("audioconvert"),
            s16,
            make("audioconvert"),
            make("audioresample"),
            sink,
        ]
        for element in chain:
            pipeline.add(element)
        link_all(*chain)
        s16.get_static_pad("src").add_probe(
            Gst.PadProbeType.BUFFER, _level_probe, weakref.ref(self)
        )
        return pipeline


def _level_probe(pad: Any, info: Any, ref: weakref.ref[AudioIn]) -> Any:
    """Streaming thread: the peak of each decoded buffer (S16LE mono)."""
    Gst = gst()
    stream = ref()
    buffer = info.get_buffer()
    if stream is None or buffer is None:
        return Gst.PadProbeReturn.OK
    # A copy (a few hundred bytes a buffer) rather than map/unmap through introspection, which
    # leaves the buffer's lock count to the binding's bookkeeping.
    data = buffer.extract_dup(0, buffer.get_size())
    samples = array("h", data[: len(data) // 2 * 2])
    peak = max((abs(v) for v in (max(samples), min(samples))), default=0) if samples else 0
    stream.buffers += 1
    stream.samples += len(samples)
    stream.peak = max(stream.peak, peak)
    if peak > SILENCE_PEAK:
        stream.loud_buffers += 1
    return Gst.PadProbeReturn.OK
