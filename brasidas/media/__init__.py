"""Media streams on GStreamer (PyGObject): the seed's PiGst* classes.

- :mod:`brasidas.media.pipeline`: :class:`~brasidas.media.pipeline.PipelineStream`, the base
  (start, pause, stop, state; failed with a reason, retried by ``supervise``).
- :mod:`brasidas.media.video`: NavCam H.264 sender and receiver (RFC 6051 capture time).
- :mod:`brasidas.media.audio`: Opus microphone out and speaker in.
- :mod:`brasidas.media.relay`: RTSP camera forwarded without re-encoding.
- :mod:`brasidas.media.gst`: GStreamer access, element creation with readable errors.
"""
