"""A real NavCam sender and receiver on loopback, the media (and, if asked, the feedback)
through a relay the test controls (``lossy_udp.LossyRelay`` or a subclass)."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator, Callable
from contextlib import AbstractAsyncContextManager
from dataclasses import dataclass
from typing import Any, Generic, TypeVar, overload

from conftest import free_udp_port
from lossy_udp import LossyRelay

from brasidas.media.video import VideoIn, VideoOut, VideoSettings

Media = TypeVar("Media", bound=LossyRelay)
Feedback = TypeVar("Feedback", bound=LossyRelay)
LOOPBACK = "127.0.0.1"


@dataclass(frozen=True)
class VideoLink(Generic[Media, Feedback]):
    sender: VideoOut
    receiver: VideoIn
    media: Media
    """Sender → receiver."""
    feedback: Feedback | None
    """Receiver → sender (RTCP: NACKs, keyframe requests), or None: straight."""


@overload
def video_link(
    media: Callable[[tuple[str, int]], Media], feedback: None = None, **settings: Any
) -> AbstractAsyncContextManager[VideoLink[Media, LossyRelay]]: ...


@overload
def video_link(
    media: Callable[[tuple[str, int]], Media],
    feedback: Callable[[tuple[str, int]], Feedback],
    **settings: Any,
) -> AbstractAsyncContextManager[VideoLink[Media, Feedback]]: ...


def video_link(
    media: Callable[[tuple[str, int]], Media],
    feedback: Callable[[tuple[str, int]], Feedback] | None = None,
    **settings: Any,
) -> AbstractAsyncContextManager[VideoLink[Media, Any]]:
    return _video_link(media, feedback, settings)


@contextlib.asynccontextmanager
async def _video_link(
    media: Callable[[tuple[str, int]], Media],
    feedback: Callable[[tuple[str, int]], Feedback] | None,
    settings: dict[str, Any],
) -> AsyncIterator[VideoLink[Media, Feedback]]:
    """Started, with the receiver's feedback going to the sender; ``settings`` are the
    sender's :class:`VideoSettings` beyond a test picture to the media relay. Stopped and
    closed on the way out."""
    receiver = VideoIn("rx", host=LOOPBACK, port=free_udp_port())
    await receiver.start()
    media_relay = media((LOOPBACK, receiver.port))
    sender = VideoOut(
        "navcam",
        VideoSettings(test_source=True, host=LOOPBACK, port=media_relay.port, **settings),
    )
    feedback_relay: Feedback | None = None
    try:
        await sender.start()
        assert sender.feedback is not None
        if feedback is None:
            receiver.set_feedback(LOOPBACK, sender.feedback.port)
        else:
            feedback_relay = feedback((LOOPBACK, sender.feedback.port))
            receiver.set_feedback(LOOPBACK, feedback_relay.port)
        yield VideoLink(sender, receiver, media_relay, feedback_relay)
    finally:
        await sender.stop()
        await receiver.stop()
        media_relay.close()
        if feedback_relay is not None:
            feedback_relay.close()
